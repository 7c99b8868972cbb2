"""The monocular VO frontend: a state machine over initialisation, tracking and relocalisation.

Per frame: ORB features (computed one frame ahead on a worker thread when the caller announces
the next frame with ``prefetch``); then, by state,

* initialising: two-view initialisation against a reference frame (``initializer``). Success
  makes the reference and the current frame keyframes 0 and 1 of the segment, with the
  triangulated points as the first map points and a two-view bundle adjustment. The frames seen
  since the reference are then posed against that map (every other one kept once there are more
  than ``backfill_frames``: a slow camera keeps one reference for hundreds of frames).
* tracking: pose from the local map (``tracker``). A frame becomes a keyframe when it tracks less
  than ``tracked_ratio`` of the last keyframe's points or ``max_interval`` has passed; the keyframe
  adds its observations, triangulates new points with its newest neighbours that have a baseline
  (``min_baseline_ratio`` of the median depth; keyframes only a frame or two apart see too little
  parallax to add points; when the camera is so slow that the whole ``triangulation_window`` lies
  within that baseline, older keyframes that still see the scene are searched), optionally records
  its points in the keyframes before it (``search_neighbours``), runs the local bundle adjustment
  (``local_ba``) and culls weak points. With the experimental ``covisible_keyframes`` it also
  links the in-view points of older covisible keyframes that the tracking window lacks
  (``SegmentMap.link_covisible``: a view half hidden for a while comes back).
* lost: relocalisation against recent keyframes of the segment; after ``patience`` frames with
  features that fail and ``patience_s`` seconds (ORB-SLAM3's "recently lost" state), the segment
  is closed and a new one initialises (``segment`` += 1). Its poses live in a new map frame: they
  are never spliced into the old one. A person walking past close to the camera hides half the
  view for a second or two, and the old map is usually found again after that; but frames lost
  while waiting may stay unposed, so ``patience_s`` is 0 (off) by default.

A frame with (almost) no features is "lost" at once and costs the patience nothing: a 20-frame
blackout ends in relocalisation if the camera comes back to a known view. A view of the map's
newest points in a strip does not count as known: a relocalised pose whose points fix its centre
``max_sigma_ratio`` times as loosely as the newest keyframe's is refused (``Tracker.relocalise``).

Frames with features that got no pose (lost while relocalisation failed, or seen before the
initialiser's final reference) are kept, the newest ``backfill_frames`` of them, and once the
camera is posed again (a new map, or relocalisation) they are tracked against the map backwards
in time from there, each from the pose of the frame after it. They come back as backfilled
results: a map loss no longer leaves the frames around it without a pose.

Intrinsics are checked twice per segment: at initialisation (the essential matrix, which assumes
K, must keep nearly the fundamental matrix's inliers) and after the first keyframes (bundle-adjusted
reprojection error). A failure logs a warning naming the likely cause; tracking goes on.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections import defaultdict
from collections.abc import Callable, Mapping, Sequence

import gtsam
import numpy as np
from scipy.spatial import cKDTree

from frontends.base import PointObservations, TrackingState, TrackResult
from frontends.mono_vo.config import KeyframeConfig, MonoVoConfig
from frontends.mono_vo.features import Features, OrbExtractor, PrefetchingExtractor, octave_sigmas
from frontends.mono_vo.geometry import frame_seed, invert, project, transform
from frontends.mono_vo.initializer import Initialisation, Initializer
from frontends.mono_vo.local_ba import local_bundle_adjustment
from frontends.mono_vo.map import KeyframeState, SegmentMap
from frontends.mono_vo.masking import Partner, dynamic_keypoints, follow_moving, inside, judge_boxes
from frontends.mono_vo.tracker import PoseEstimate, Tracker
from frontends.mono_vo.triangulation import triangulate_new_points
from frontends.orb import hamming
from frontends.types import CameraIntrinsics, Frame, Keyframe

log = logging.getLogger(__name__)


class MonoVo:
    """Monocular visual odometry with a local map, local bundle adjustment and map segments."""

    name = "mono-vo"

    def __init__(self, camera: CameraIntrinsics, config: MonoVoConfig) -> None:
        self.camera = camera
        self.config = config
        self.K = camera.K
        self.extractor = OrbExtractor(config.orb, camera)
        self.features = PrefetchingExtractor(self.extractor)
        count_scale = self.extractor.budget / config.orb.nfeatures
        self.min_features = max(10, round(config.min_features * count_scale))
        self.triangulation_radius = config.keyframes.search_fraction * float(
            np.hypot(camera.width, camera.height)
        )
        self.octave_sigma = config.orb.scale_factor ** np.arange(config.orb.levels, dtype=np.float64)
        self.initializer = Initializer(
            config.init, self.K, count_scale, config.seed, float(np.hypot(camera.width, camera.height))
        )
        self.tracker = Tracker(
            config.tracking, config.relocalisation, self.K, self.octave_sigma,
            (camera.width, camera.height), count_scale, config.seed,
        )  # fmt: skip
        self.segment_map = SegmentMap(0, self.octave_sigma)
        self.all_keyframes: list[KeyframeState] = []
        self.mode: TrackingState = "initialising"
        self.T_cw_last: np.ndarray | None = None
        #: Constant-velocity model: last inter-frame motion (T_cw(k) = velocity @ T_cw(k-1)).
        self.velocity = np.eye(4)
        self.last_frame_index = -1
        self.last_timestamp = 0.0
        self.failed_relocalisations = 0
        #: Timestamp of the first failed relocalisation since tracking was lost.
        self.lost_since: float | None = None
        #: Frames seen since the initialisation reference: posed against the new map once it exists.
        self.pending: list[tuple[int, float, Features]] = []
        #: Frames with features and no pose, before ``pending`` (lost, or the initialiser's earlier
        #: references): tracked backwards once the camera is posed again.
        self.unposed: list[tuple[int, float, Features]] = []
        #: Boxes of objects that move on their own in a frame (``set_dynamic_objects``), and the
        #: path of the initialisation reference frame (the provider may look frames up by path).
        self.dynamic_objects: Callable[[Frame], Sequence[Sequence[float]]] | None = None
        self.reference_path: str | None = None
        #: The newest keyframe's timestamp and its boxes judged moving (``masking.follow_iou``).
        self.moving_boxes: tuple[float, list[tuple[float, float, float, float]]] = (-np.inf, [])
        self.intrinsics_warned = False
        #: Seconds spent per stage (orb, initialise, track, keyframe, bundle_adjustment, relocalise);
        #: "orb" is the wait for the features, which is less than extraction when they are prefetched.
        self.stage_seconds: dict[str, float] = defaultdict(float)

    # -- the Frontend protocol --------------------------------------------------------------------

    def prefetch(self, frame: Frame) -> None:
        self.features.prefetch(frame, lambda: frame.gray)

    def track(self, frame: Frame) -> TrackResult:
        start = time.perf_counter()
        features = self.features.extract(frame, lambda: frame.gray)
        self.stage_seconds["orb"] += time.perf_counter() - start
        if len(features) < self.min_features:
            if self.mode != "initialising":
                self.mode = "lost"
            return self._result(frame, "lost")
        if self.mode == "initialising":
            return self._timed("initialise", self._initialise, frame, features)
        tree = cKDTree(features.points)
        if self.mode == "tracking":
            result = self._timed("track", self._track, frame, features, tree)
            if result is not None:
                return result
            self.mode = "lost"
        return self._timed("relocalise", self._relocalise, frame, features, tree)

    @property
    def keyframes_in_flux(self) -> int:
        """Local bundle adjustment moves the newest ``ba.window`` keyframes; older ones stay put."""
        return self.config.ba.window if self.config.ba.enabled else 0

    def keyframes(self) -> list[Keyframe]:
        for kf in self.segment_map.keyframes:
            self._sync_output(kf)
        return [kf.output for kf in self.all_keyframes]

    # -- states ------------------------------------------------------------------------------------

    def _initialise(self, frame: Frame, features: Features) -> TrackResult:
        init = self.initializer.try_frame(frame.index, frame.timestamp, features, frame.image)
        if init is None:
            reference = self.initializer.reference
            if reference is not None and reference.index == frame.index:
                self.reference_path = frame.path
            self.pending.append((frame.index, frame.timestamp, features))
            if reference is not None:
                self._keep_unposed([p for p in self.pending if p[0] < reference.index])
                self.pending = [p for p in self.pending if p[0] >= reference.index]
            if len(self.pending) > self.config.relocalisation.backfill_frames + 1:
                # A slow camera keeps one reference for hundreds of frames: every other frame is kept
                # (memory and the backfill stay bounded); the others stay unposed ("initialising").
                self.pending = self.pending[::2]
            return self._result(frame, "initialising")
        self._check_essential_share(init)
        reference_frame = Frame(
            init.reference_index, init.reference_timestamp, init.reference_image, self.reference_path
        )
        first = self._new_keyframe(reference_frame, np.eye(4), init.reference)
        second = self._new_keyframe(frame, init.T_cw, features)
        first_boxes, second_boxes = self._boxes(reference_frame), self._boxes(frame)
        first.dynamic = self._dynamic_keypoints(first, first_boxes, second)
        second.dynamic = self._dynamic_keypoints(second, second_boxes, first)
        static = ~first.dynamic[init.reference_idx] & ~second.dynamic[init.current_idx]
        ids = self.segment_map.points.add(init.points_w[static], first.id)
        self.segment_map.observe(first, init.reference_idx[static], ids)
        self.segment_map.observe(second, init.current_idx[static], ids)
        self._bundle_adjust()
        second.output.odometry_covariance = self._odometry_covariance(first, second)
        steps = max(1, frame.index - init.reference_index)
        self.velocity = _fraction_of_motion(second.T_cw @ invert(first.T_cw), 1.0 / steps)
        self.mode = "tracking"
        self.failed_relocalisations = 0
        first_sigma = self._keyframe_centre_sigma(first)
        backfilled = self._track_backwards(first.T_cw, first.frame_index, first_sigma) + self._backfill(
            first, second, first_sigma
        )
        return dataclasses.replace(
            self._tracked(frame, second.T_cw, "tracking", second), backfilled=backfilled
        )

    def _backfill(
        self, first: KeyframeState, second: KeyframeState, reference_sigma: float
    ) -> tuple[TrackResult, ...]:
        """Poses of the frames seen while initialising: the reference is keyframe 0; the frames
        between it and the second keyframe are tracked against the new map from an interpolated
        prediction. A frame that does not track (``_track_late``) keeps its "initialising" result."""
        results = [
            TrackResult(
                first.frame_index, first.timestamp, "tracking", invert(first.T_cw),
                self.segment_map.segment, first.output,
            )
        ]  # fmt: skip
        span = second.frame_index - first.frame_index
        motion = second.T_cw @ invert(first.T_cw)
        for index, timestamp, features in self.pending:
            if not first.frame_index < index < second.frame_index:
                continue
            predicted = _fraction_of_motion(motion, (index - first.frame_index) / span) @ first.T_cw
            late = self._track_late(index, timestamp, features, predicted, reference_sigma)
            if late is not None:
                results.append(late)
        self.pending = []
        return tuple(results)

    def _track(self, frame: Frame, features: Features, tree: cKDTree) -> TrackResult | None:
        assert self.T_cw_last is not None
        steps = max(1, frame.index - self.last_frame_index)
        predicted = _fraction_of_motion(self.velocity, steps) @ self.T_cw_last
        elapsed = max(frame.timestamp - self.last_timestamp, 0.0)
        rotation_sigma = float(np.radians(self.config.tracking.rotation_prior_acceleration)) * elapsed**2
        estimate = self.tracker.track(
            self.segment_map, features, tree, predicted, frame.index, rotation_sigma
        )
        if estimate is None:
            return None
        self.velocity = _fraction_of_motion(estimate.T_cw @ invert(self.T_cw_last), 1.0 / steps)
        keyframe = None
        if self._needs_keyframe(frame, features, estimate):
            keyframe = self._timed("keyframe", self._add_keyframe, frame, features, estimate)
        return self._tracked(frame, estimate.T_cw, "tracking", keyframe, _observations(features, estimate))

    def _relocalise(self, frame: Frame, features: Features, tree: cKDTree) -> TrackResult:
        max_sigma = self.config.relocalisation.max_sigma_ratio * self._keyframe_centre_sigma(
            self.segment_map.keyframes[-1]
        )
        estimate = self.tracker.relocalise(self.segment_map, features, tree, frame.index, max_sigma)
        if estimate is not None:
            log.info("frame %d: relocalised in segment %d", frame.index, self.segment_map.segment)
            self.mode = "tracking"
            self.failed_relocalisations = 0
            self.velocity = np.eye(4)
            return dataclasses.replace(
                self._tracked(frame, estimate.T_cw, "relocalised", None, _observations(features, estimate)),
                backfilled=self._track_backwards(
                    estimate.T_cw,
                    frame.index,
                    self._centre_sigma(estimate.T_cw, features, estimate.keypoint_idx, estimate.point_ids),
                ),
            )
        self._keep_unposed([(frame.index, frame.timestamp, features)])
        self.failed_relocalisations += 1
        lost_since = getattr(self, "lost_since", None)  # None also in checkpoints from before
        if self.failed_relocalisations == 1 or lost_since is None:
            self.lost_since = lost_since = frame.timestamp
        settings = self.config.relocalisation
        if (
            self.failed_relocalisations >= settings.patience
            and frame.timestamp - lost_since >= settings.patience_s
        ):
            self._start_segment(frame)
        return self._result(frame, "lost")

    def _keep_unposed(self, frames: Sequence[tuple[int, float, Features]]) -> None:
        kept = [*self.unposed, *frames]
        self.unposed = kept[len(kept) - min(self.config.relocalisation.backfill_frames, len(kept)) :]

    def _track_backwards(
        self, T_cw: np.ndarray, frame_index: int, reference_sigma: float
    ) -> tuple[TrackResult, ...]:
        """Pose the kept unposed frames before ``frame_index`` (posed at ``T_cw``) against the
        current map, newest first, each predicted from the frame after it with the inverse of the
        constant-velocity motion; a frame that does not track (``_track_late``) stays unposed."""
        results = []
        backwards = invert(self.velocity)
        later_pose, later_index = T_cw, frame_index
        for index, timestamp, features in reversed(self.unposed):
            if index >= frame_index:
                continue
            predicted = _fraction_of_motion(backwards, later_index - index) @ later_pose
            late = self._track_late(index, timestamp, features, predicted, reference_sigma)
            if late is not None and late.pose is not None:
                results.append(late)
                later_pose, later_index = invert(late.pose), index
        self.unposed = []
        return tuple(reversed(results))

    def _centre_sigma(
        self, T_cw: np.ndarray, features: Features, keypoint_idx: np.ndarray, point_ids: np.ndarray
    ) -> float:
        return self.tracker.centre_sigma(self.segment_map, T_cw, features, keypoint_idx, point_ids)

    def _keyframe_centre_sigma(self, kf: KeyframeState) -> float:
        """How loosely a keyframe's map points fix its camera centre (``Tracker.centre_sigma``)."""
        ids = self.segment_map.live_ids(kf)
        seen = np.flatnonzero(ids >= 0)
        return self._centre_sigma(kf.T_cw, kf.features, seen, ids[seen])

    def _track_late(
        self, index: int, timestamp: float, features: Features, predicted: np.ndarray, reference_sigma: float
    ) -> TrackResult | None:
        """A frame seen earlier, tracked against the current map from ``predicted`` (T_cw); None when
        it does not track or its inliers fix its camera centre more than ``backfill_max_sigma_ratio``
        times as loosely as the frame tracking resumed from (``reference_sigma``)."""
        estimate = self.tracker.track(self.segment_map, features, cKDTree(features.points), predicted, index)
        if estimate is None:
            return None
        limit = self.config.relocalisation.backfill_max_sigma_ratio * reference_sigma
        if self._centre_sigma(estimate.T_cw, features, estimate.keypoint_idx, estimate.point_ids) > limit:
            return None
        pose, seen = invert(estimate.T_cw), _observations(features, estimate)
        return TrackResult(index, timestamp, "tracking", pose, self.segment_map.segment, observations=seen)

    def _start_segment(self, frame: Frame) -> None:
        for kf in self.segment_map.keyframes:
            self._sync_output(kf)
        segment = self.segment_map.segment + 1
        log.warning(
            "frame %d: relocalisation failed %d times; starting map segment %d",
            frame.index, self.failed_relocalisations, segment,
        )  # fmt: skip
        self.segment_map = SegmentMap(segment, self.octave_sigma)
        self.initializer.reset()
        self.pending = []
        self.mode = "initialising"
        self.T_cw_last = None
        self.failed_relocalisations = 0

    # -- keyframes ---------------------------------------------------------------------------------

    def _needs_keyframe(self, frame: Frame, features: Features, estimate: PoseEstimate) -> bool:
        s = self.config.keyframes
        last = self.segment_map.keyframes[-1]
        elapsed = frame.timestamp - last.timestamp
        if elapsed < s.min_interval:
            return False
        # ORB-SLAM counts only the last keyframe's established points (seen by >= 3 keyframes).
        ids = self.segment_map.live_ids(last)
        observations = self.segment_map.points.observations[ids[ids >= 0]]
        established = int((observations >= min(3, len(self.segment_map.keyframes))).sum())
        tracked = len(estimate.keypoint_idx)
        # The second test catches fast forward motion, where the map thins out before points establish.
        return (
            tracked < s.tracked_ratio * established
            or tracked < s.min_tracked_share * len(observations)
            or elapsed >= s.max_interval
            or (elapsed >= s.narrow_min_interval and self._tracked_in_a_strip(features, estimate))
        )

    def _tracked_in_a_strip(self, features: Features, estimate: PoseEstimate) -> bool:
        spread = np.ptp(features.points[estimate.keypoint_idx], axis=0)
        limit = self.config.keyframes.min_tracked_spread * np.array([self.camera.width, self.camera.height])
        return bool((spread < limit).any())

    def _add_keyframe(self, frame: Frame, features: Features, estimate: PoseEstimate) -> KeyframeState:
        previous = self.segment_map.keyframes[-1]
        keyframe = self._new_keyframe(frame, estimate.T_cw, features)
        neighbours = self._triangulation_neighbours(keyframe, estimate)
        keyframe.dynamic = self._dynamic_keypoints(
            keyframe, self._boxes(frame), neighbours[0] if neighbours else previous
        )
        static = ~keyframe.dynamic[estimate.keypoint_idx]
        self.segment_map.observe(keyframe, estimate.keypoint_idx[static], estimate.point_ids[static])
        # A map point matched inside a moving object's box lies on it (the object hides what is
        # behind): it was mapped while the detector missed the object, and it moves.
        self.segment_map.points.alive[estimate.point_ids[~static]] = False
        for neighbour in neighbours:
            triangulate_new_points(
                self.segment_map, keyframe, neighbour, self.K, self.octave_sigma, self.config.keyframes,
                self.config.tracking.inlier_threshold, self.triangulation_radius,
            )  # fmt: skip
        self._observe_in_neighbours(keyframe)
        self._fuse_duplicates(keyframe)
        self._bundle_adjust()
        self.segment_map.cull(keyframe.id)
        t = self.config.tracking
        self.segment_map.link_covisible(
            keyframe, t.local_keyframes, t.covisible_reach, t.covisible_keyframes, t.covisible_min_shared,
            lambda ids: self._in_view(keyframe.T_cw, ids),
        )  # fmt: skip
        keyframe.output.odometry_covariance = self._odometry_covariance(previous, keyframe)
        return keyframe

    def _observe_in_neighbours(self, keyframe: KeyframeState) -> None:
        """Project the new keyframe's points into the recent keyframes and record them where an
        unmapped keypoint matches (ORB-SLAM's SearchInNeighbors): a point triangulated by the new
        keyframe and one partner is otherwise only ever seen by later keyframes, so its depth rests
        on the shortest baselines and most die unconfirmed."""
        count = self.config.keyframes.search_neighbours
        if count <= 0:
            return
        ids = self.segment_map.live_ids(keyframe)
        ids = np.unique(ids[ids >= 0])
        for neighbour in self.segment_map.keyframes[-1 - count : -1]:
            own = self.segment_map.live_ids(neighbour)
            candidates = ids[~np.isin(ids, own)]
            if len(candidates) == 0:
                continue
            keypoint_idx, point_ids = self.tracker.search_by_projection(
                self.segment_map, candidates, neighbour.features, cKDTree(neighbour.features.points),
                neighbour.T_cw, self.config.keyframes.search_radius,
            )  # fmt: skip
            free = (own[keypoint_idx] < 0) & ~neighbour.dynamic[keypoint_idx]
            keypoint_idx, point_ids = keypoint_idx[free], point_ids[free]
            fits = self.tracker.fits(
                self.segment_map, neighbour.features, keypoint_idx, point_ids, neighbour.T_cw
            )
            self.segment_map.observe(neighbour, keypoint_idx[fits], point_ids[fits], newest=False)

    def _fuse_duplicates(self, keyframe: KeyframeState) -> None:
        """Merge local-map points the new keyframe sees at a keypoint that holds another point."""
        max_hamming = self.config.keyframes.fuse_max_hamming
        if max_hamming:
            self.segment_map.fuse(*self.duplicate_pairs(keyframe, max_hamming))

    def duplicate_pairs(self, keyframe: KeyframeState, max_hamming: int) -> tuple[np.ndarray, np.ndarray]:
        """(point the keyframe holds, local-map point it does not hold) pairs that are one scene
        point: the second projects within ``search_radius`` px of the first's keypoint, fits there
        and its descriptor is within ``max_hamming`` bits of the keypoint's."""
        none = np.zeros(0, np.int64)
        own = self.segment_map.live_ids(keyframe)
        local = self.segment_map.local_point_ids(self.config.tracking.local_keyframes)
        candidates = local[~np.isin(local, own)]
        if len(candidates) == 0:
            return none, none
        features = keyframe.features
        keypoint_idx, point_ids = self.tracker.search_by_projection(
            self.segment_map, candidates, features, cKDTree(features.points), keyframe.T_cw,
            self.config.keyframes.search_radius,
        )  # fmt: skip
        held = own[keypoint_idx]
        occupied = held >= 0
        keypoint_idx, point_ids, held = keypoint_idx[occupied], point_ids[occupied], held[occupied]
        close = hamming(self.segment_map.points.descriptors[point_ids], features.descriptors[keypoint_idx])
        same = (close <= max_hamming) & self.tracker.fits(
            self.segment_map, features, keypoint_idx, point_ids, keyframe.T_cw
        )
        return held[same], point_ids[same]

    def _in_view(self, T_cw: np.ndarray, point_ids: np.ndarray) -> np.ndarray:
        """Which map points project in front of the camera at ``T_cw`` and within its image, or
        within a quarter of the image beyond its borders (where the next frames may bring them)."""
        uv, depth = project(self.K, T_cw, self.segment_map.points.positions[point_ids])
        size = np.array([self.camera.width, self.camera.height])
        return (depth > 0) & np.all((uv >= -0.25 * size) & (uv < 1.25 * size), axis=1)

    def _triangulation_neighbours(
        self, keyframe: KeyframeState, estimate: PoseEstimate
    ) -> list[KeyframeState]:
        """The earlier keyframes to triangulate with (``triangulation_partners``)."""
        s = self.config.keyframes
        depths = transform(keyframe.T_cw, self.segment_map.points.positions[estimate.point_ids])[:, 2]
        median_depth = float(np.median(depths)) if len(depths) else 0.0
        center = invert(keyframe.T_cw)[:3, 3]

        def baseline(other: KeyframeState) -> float:
            return float(np.linalg.norm(invert(other.T_cw)[:3, 3] - center))

        def seen(other: KeyframeState) -> int:
            """How many of the tracked points ``other`` observes."""
            return int(np.isin(self.segment_map.live_ids(other), estimate.point_ids).sum())

        recent = list(reversed(self.segment_map.keyframes[-1 - s.triangulation_window : -1]))
        baselines = [baseline(other) for other in recent]
        shared = [seen(other) for other in recent]
        tracked = len(estimate.point_ids)
        chosen = [recent[i] for i in triangulation_partners(baselines, shared, tracked, median_depth, s)]
        if len(chosen) < s.triangulation_neighbours:
            # A slow camera makes keyframes closer together than the baseline: the window's all lie within
            # it and no new point is made until the map starves (docs/2026-12-07-slow-camera.md). Older
            # keyframes that still see the scene (as ORB-SLAM's covisible ones) take their place.
            older = self.segment_map.keyframes[-1 - s.triangulation_reach : -1 - s.triangulation_window]
            near = s.min_baseline_ratio * median_depth
            for other in reversed(older):
                if len(chosen) >= s.triangulation_neighbours:
                    break
                if baseline(other) >= near and seen(other) >= s.far_partner_min_shared * tracked:
                    chosen.append(other)
        return chosen

    def _new_keyframe(self, frame: Frame, T_cw: np.ndarray, features: Features) -> KeyframeState:
        output = Keyframe(
            id=len(self.all_keyframes), frame_index=frame.index, timestamp=frame.timestamp,
            pose=invert(T_cw), keypoints=features.keypoints, descriptors=features.descriptors,
            image=frame.image, segment=self.segment_map.segment,
            keypoint_sigmas=octave_sigmas(self.octave_sigma, features.octaves),
        )  # fmt: skip
        state = KeyframeState(
            output.id,
            frame.index,
            frame.timestamp,
            T_cw.copy(),
            features,
            np.full(len(features), -1, np.int64),
            output,
            np.zeros(len(features), bool),
            self.segment_map.keyframes[-1].scale if self.segment_map.keyframes else 1.0,
        )
        self.segment_map.keyframes.append(state)
        self.all_keyframes.append(state)
        return state

    def apply_correction(self, poses: Mapping[int, np.ndarray]) -> None:
        """Move the current segment to the loop-corrected ``poses`` (camera-to-world Sim(3) by
        keyframe id, this segment's map frame): each keyframe to its pose, each map point with the
        keyframe that created it, the last frame with the newest keyframe (the constant-velocity
        model's translation scaled with it). Tracking then continues in the corrected map, so the
        next odometry steps agree with the loop instead of pulling the map back.

        The newest keyframes, those tracking and local bundle adjustment use, all move with the
        newest keyframe's correction as one rigid similarity: the pose graph spreads the loop's
        rotation over every odometry edge, and that small per-keyframe turn changes what short
        baselines triangulate. Measured on synthetic loop 1: with per-keyframe corrections the
        next local bundle adjustment, anchored on the older corrected keyframes, pulled the window
        back to its old scale (6 % of the 7 % the loop asked for), and every later keyframe
        inherited that wrong scale step."""
        corrections: dict[int, np.ndarray] = {}
        for kf in self.segment_map.keyframes:
            if kf.id in poses:
                # World-to-world similarity that takes the keyframe's old camera to its new one.
                corrections[kf.id] = np.asarray(poses[kf.id], dtype=np.float64) @ np.linalg.inv(
                    _similarity(kf)
                )
        if not corrections:
            return
        local = [kf.id for kf in self.segment_map.keyframes[-self._local_map_keyframes() :]]
        newest_corrected = max((i for i in local if i in corrections), default=None)
        if newest_corrected is not None:
            for kf_id in local:
                corrections[kf_id] = corrections[newest_corrected]
        for kf in self.segment_map.keyframes:
            if kf.id in corrections:
                kf.T_cw = invert(_without_scale(corrections[kf.id] @ invert(kf.T_cw)))
                kf.scale *= float(np.cbrt(np.linalg.det(corrections[kf.id][:3, :3])))
        points = self.segment_map.points
        known = np.array(sorted(corrections))
        newest = self.segment_map.keyframes[-1].id
        # Each point moves with the keyframe that created it; points of keyframes without a
        # correction move with the newest corrected one. One gather per point, not a pass over all
        # points per keyframe (0.56 s at 100 000 points, 850 keyframes: docs/2026-12-07-backend-cost.md).
        stacked = np.stack([corrections[int(k)] for k in known])
        scales = np.cbrt(np.linalg.det(stacked[:, :3, :3]))
        slot = np.minimum(np.searchsorted(known, points.first_keyframe), len(known) - 1)
        slot[known[slot] != points.first_keyframe] = len(known) - 1
        rotations = stacked[slot, :3, :3]
        points.positions[:] = np.einsum("pij,pj->pi", rotations, points.positions) + stacked[slot, :3, 3]
        # What the projection checks know of a point moves with it: the mean viewing direction
        # turns with the rotation, the distance range over which its descriptor holds scales.
        scale = scales[slot]
        points.normals[:] = np.einsum("pij,pj->pi", rotations, points.normals) / scale[:, None]
        points.min_distance *= scale
        points.max_distance *= scale
        last = corrections.get(newest, corrections[int(known[-1])])
        if self.T_cw_last is not None:
            self.T_cw_last = invert(_without_scale(last @ invert(self.T_cw_last)))
        self.velocity[:3, 3] *= float(np.cbrt(np.linalg.det(last[:3, :3])))
        for kf in self.segment_map.keyframes:
            self._sync_output(kf)

    def _local_map_keyframes(self) -> int:
        """How many of the newest keyframes tracking and local bundle adjustment touch."""
        return max(self.config.tracking.local_keyframes, self.config.ba.window + self.config.ba.max_fixed)

    def set_dynamic_objects(self, provider: Callable[[Frame], Sequence[Sequence[float]]] | None) -> None:
        """Keypoints of a new keyframe inside a box ``provider(frame)`` returns (x0, y0, x1, y1 of
        objects that can move on their own: people, vehicles, animals) never become or observe map
        points (DynaSLAM masks them for the same reason): a point triangulated on a walking person
        fits its two views with a wrong depth and, once the person fills the view, drags the pose
        along (measured on the synthetic loops: 4-9 % ATE with moving people, 0.3-0.4 % without).
        A box with a fifth value > 0 (a vehicle, often parked) stays in the map when its points fit
        the camera motion; boxes not seen to move are masked only while enough of the image stays
        unmasked (``masking``; docs/2026-12-06-masking.md). Called on keyframes only, so a CNN
        detector costs what it costs the loop detector."""
        self.dynamic_objects = provider

    def _boxes(self, frame: Frame) -> list[Sequence[float]]:
        """The provider's boxes (x0, y0, x1, y1[, may_keep]) of ``frame``."""
        return [] if self.dynamic_objects is None else list(self.dynamic_objects(frame))

    def _dynamic_keypoints(
        self, keyframe: KeyframeState, boxes: Sequence[Sequence[float]], partner: KeyframeState
    ) -> np.ndarray:
        """Which of the keyframe's keypoints to keep out of the map (``masking.dynamic_keypoints``),
        its ``boxes`` judged against the ``partner`` keyframe."""
        features, settings = keyframe.features, self.config.masking
        if not boxes or len(features) == 0:
            return np.zeros(len(features), bool)
        if not settings.check_motion:
            return np.any([inside(features.keypoints, box) for box in boxes], axis=0)
        may_keep = [len(box) > 4 and float(box[4]) > 0 for box in boxes]
        evidence, background = judge_boxes(
            boxes, features, keyframe.T_cw, Partner(partner.features, partner.T_cw), self.K,
            self.octave_sigma, float(np.hypot(self.camera.width, self.camera.height)), settings,
            frame_seed(self.config.seed, keyframe.frame_index, 5),
        )  # fmt: skip
        # A keyframe whose detector saw nothing keeps the memory: detectors miss objects now and then.
        since, moving_before = self.moving_boxes
        recent = moving_before if keyframe.timestamp - since <= settings.follow_seconds else []
        evidence = follow_moving(evidence, recent, settings.follow_iou)
        self.moving_boxes = (keyframe.timestamp, [e.box for e in evidence if e.verdict == "moving"])
        dynamic = dynamic_keypoints(features.keypoints, evidence, may_keep, settings)
        log.debug(
            "frame %d (against frame %d): %d of %d keypoints masked; background violations %.2f; "
            "boxes (verdict, keypoints, matches, violations, depth ratio) %s",
            keyframe.frame_index, partner.frame_index, int(dynamic.sum()), len(features), background,
            [(e.verdict, e.keypoints, e.matches, e.violations, round(e.depth_ratio, 2)) for e in evidence],
        )  # fmt: skip
        return dynamic

    def _bundle_adjust(self) -> None:
        if not self.config.ba.enabled:
            return
        start = time.perf_counter()
        stats = local_bundle_adjustment(self.segment_map, self.K, self.octave_sigma, self.config.ba)
        self.stage_seconds["bundle_adjustment"] += time.perf_counter() - start
        for kf in self.segment_map.keyframes[-self.config.ba.window :]:
            self._sync_output(kf)
        check = self.config.intrinsics_check
        if (
            stats is not None
            and len(self.segment_map.keyframes) == check.check_after_keyframes
            and stats.median_error_px > check.max_median_reprojection_px
        ):
            self._warn_intrinsics(
                f"median reprojection error {stats.median_error_px:.2f} px after bundle adjustment of the "
                f"first {check.check_after_keyframes} keyframes "
                f"(expected < {check.max_median_reprojection_px} px)"
            )

    def _odometry_covariance(self, previous: KeyframeState, current: KeyframeState) -> np.ndarray:
        """Covariance of the Sim(3) motion between two keyframes: rotation, translation, log-scale,
        inflated when they share few map points (``KeyframeConfig.covariance_exponent``)."""
        s = self.config.keyframes
        inflation = covariance_inflation(self.segment_map.shared_points(previous, current), s)
        distance = float(np.linalg.norm(invert(current.T_cw)[:3, 3] - invert(previous.T_cw)[:3, 3]))
        sigmas = (
            inflation
            * np.r_[
                np.full(3, np.radians(s.rotation_sigma_deg)),
                np.full(3, max(s.translation_sigma_ratio * distance, 1e-6)),
                s.log_scale_sigma,
            ]
        )
        return np.diag(sigmas**2)

    def _sync_output(self, kf: KeyframeState) -> None:
        """Refresh the API keyframe (of the current segment) from its pose and the map points."""
        kf.output.pose = _similarity(kf)
        ids = self.segment_map.live_ids(kf)
        points3d = np.full((len(ids), 3), np.nan)
        mapped = ids >= 0
        points3d[mapped] = transform(kf.T_cw, self.segment_map.points.positions[ids[mapped]]) / kf.scale
        kf.output.points3d = points3d
        kf.output.point_ids = ids.copy()

    # -- intrinsics check --------------------------------------------------------------------------

    def _check_essential_share(self, init: Initialisation) -> None:
        minimum = self.config.intrinsics_check.min_essential_share
        if init.essential_share < minimum:
            self._warn_intrinsics(
                f"the essential matrix keeps only {init.essential_share:.0%} of the fundamental matrix's "
                f"inliers at initialisation (expected >= {minimum:.0%})"
            )

    def _warn_intrinsics(self, evidence: str) -> None:
        if self.intrinsics_warned:
            return
        self.intrinsics_warned = True
        c = self.camera
        log.warning(
            "camera intrinsics look wrong (fx=%.1f fy=%.1f cx=%.1f cy=%.1f from %s): %s; check the "
            "calibration (--calib), the trajectory is unreliable",
            c.fx, c.fy, c.cx, c.cy, c.source or "unknown source", evidence,
        )  # fmt: skip

    # -- helpers -----------------------------------------------------------------------------------

    def _tracked(
        self,
        frame: Frame,
        T_cw: np.ndarray,
        state: TrackingState,
        keyframe: KeyframeState | None,
        observations: PointObservations | None = None,
    ) -> TrackResult:
        self.T_cw_last = T_cw
        self.last_frame_index = frame.index
        self.last_timestamp = frame.timestamp
        return TrackResult(
            frame.index, frame.timestamp, state, invert(T_cw), self.segment_map.segment,
            keyframe.output if keyframe is not None else None, observations=observations,
        )  # fmt: skip

    def _result(self, frame: Frame, state: TrackingState) -> TrackResult:
        return TrackResult(frame.index, frame.timestamp, state, None, self.segment_map.segment)

    def _timed(self, stage: str, function, *args):  # type: ignore[no-untyped-def]
        start = time.perf_counter()
        try:
            return function(*args)
        finally:
            self.stage_seconds[stage] += time.perf_counter() - start


def triangulation_partners(
    baselines: Sequence[float],
    shared: Sequence[int],
    tracked: int,
    median_depth: float,
    settings: KeyframeConfig,
) -> list[int]:
    """Indices into the recent keyframes (newest first; their ``baselines`` to the new keyframe and
    the ``shared`` map points with its ``tracked`` ones) of its triangulation partners. Candidates
    see the same scene (``partner_min_shared`` of the tracked points; any keyframe when none does)
    with a baseline of ``min_baseline_ratio`` x the median depth; the newest with
    ``preferred_baseline_ratio`` come first, then the newest others."""
    near = settings.min_baseline_ratio * median_depth
    usable = [i for i, b in enumerate(baselines) if b >= near]
    covisible = [i for i in usable if shared[i] >= settings.partner_min_shared * tracked]
    candidates = covisible or usable
    wide = [i for i in candidates if baselines[i] >= settings.preferred_baseline_ratio * median_depth]
    return (wide + [i for i in candidates if i not in wide])[: settings.triangulation_neighbours]


def covariance_inflation(shared_points: int, settings: KeyframeConfig) -> float:
    """Factor on the odometry sigmas of two keyframes that share ``shared_points`` map points."""
    shortfall = max(1.0, settings.covariance_reference_points / max(shared_points, 1))
    return float(min(shortfall**settings.covariance_exponent, settings.max_covariance_inflation))


def _observations(features: Features, estimate: PoseEstimate) -> PointObservations:
    return PointObservations(features.keypoints[estimate.keypoint_idx], estimate.point_ids.copy())


def _fraction_of_motion(T: np.ndarray, fraction: float) -> np.ndarray:
    """``T ** fraction`` on SE(3) (e.g. the per-frame share of a motion over several frames)."""
    if fraction == 1.0:
        return T.copy()
    return np.asarray(gtsam.Pose3.Expmap(fraction * gtsam.Pose3.Logmap(gtsam.Pose3(T))).matrix())


def _similarity(kf: KeyframeState) -> np.ndarray:
    """Camera-to-world Sim(3) of a keyframe: its pose with the scale corrections gave it."""
    pose = invert(kf.T_cw)
    pose[:3, :3] *= kf.scale
    return pose


def _without_scale(matrix: np.ndarray) -> np.ndarray:
    pose = np.array(matrix, dtype=np.float64)
    pose[:3, :3] /= float(np.cbrt(np.linalg.det(pose[:3, :3])))
    return pose
