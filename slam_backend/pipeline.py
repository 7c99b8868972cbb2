"""Loop closing: keyframes -> object detector -> loop detector -> verifier -> pose graph.

``LoopClosing`` consumes what a frontend says about each frame (``TrackResult``, including the
results it backfills) and keeps two trajectories of every posed frame:

* **odometry**: keyframe poses chained from the odometry steps the backend receives (the step of a
  keyframe is its pose in the previous keyframe's frame, read once the keyframe has *settled*, see
  below), and each frame anchored to the newest keyframe of its segment at the time it was posed
  (``anchor ∘ relative``) and to the segment's next keyframe (through the two keyframes' poses
  when that one arrived), the two estimates blended by the frame's share of the time between them;
  a keyframe's own frame is the keyframe;
* **loop-closed**: the same frames anchored to the backend's current Sim(3) keyframe estimates.

Why both anchors: a keyframe step changes after the frames before it were tracked (local BA,
settling, loop corrections); anchored to the older keyframe alone, the frames carried none of that
and the trajectory jumped at every keyframe. On the 9 synthetic benchmark scenes the loop-closed
frames were 1.6-3x worse than the keyframes (loop 0: 0.019 vs 0.006 m); with both anchors and the
keyframe's frame on the keyframe, geometric-mean ATE after loop closing went 0.026 -> 0.019 m.

With no accepted loop the two coincide, so "the trajectory is unchanged" is a measurable claim.

Per keyframe: objects (the object detector sees the keyframe's image; a failing detector costs the
keyframe its objects, logged and counted), loop candidates (a failing detector costs the query its
candidates), verification of the best ``max_verifications`` candidates at or above the detector's
threshold (a raising verifier counts as a rejection with the error as reason; one that takes longer
than ``verify_timeout_s`` as a rejection with reason "timeout ..."; a candidate whose match is
covisible with a better candidate's that failed on the maps alone is not verified:
docs/2026-12-07-covisible-candidates.md), and one backend event
with every verified loop of the query. The backend's outlier rejection (PCM + GNC by default) makes
the final decision; ``loops()`` reports the current decision of every candidate.
Verification runs on a worker thread while the frontend tracks the next frames
(``overlap_verification``; pycolmap and OpenCV release the GIL for most of it): a keyframe's loops
are decided when the next keyframe settles, or at ``finish()``, so the run's decisions do not depend
on timing. The worker gets shallow copies of the two keyframes, taken when it starts, because the
frontend re-assigns a keyframe's pose and points while it works.

Settling: a frontend's local bundle adjustment keeps moving its newest keyframes after it hands
them out (``SettlingFrontend.keyframes_in_flux``, mono-vo: its BA window of 6). A keyframe goes to
the backend and the loop detector only once that many newer keyframes of its segment exist (or its
segment ended, or ``finish()``), so its odometry step is read from poses that no longer change
(the first keyframe of a new segment waits for at least one, see below). Read at arrival instead,
the steps of the first keyframes after a monocular initialisation were off by 0.6-0.8 deg and
20-35 % in scale (synthetic loop 0, keyframes 2-5; 0.04-0.13 deg once adjusted), and PCM then
rejected the correct loops that reached back to them as inconsistent with that chain (23 of 36
verified loops). Loops are found ``keyframes_in_flux`` keyframes later.

A new map segment (the frontend could not relocalise) is linked to the previous keyframe by a
step with a very loose covariance (``segment_link_*``): the map stays one graph, and a loop that
reaches back across the gap pulls the segment into place. The step's mean bridges the gap at
constant velocity (``segment_link_speed_window_s``): the camera moves on at the old segment's recent
speed and direction for the time between the two keyframes, keeps its orientation, and the new
segment's map units are scaled so that its own recent speed matches the old one. A monocular map
restarts at an arbitrary scale (its first baseline), so without this the odometry after a restart
was off by the ratio of the two scales (synthetic loop 2: 3x) even where each segment was right.

Deferred loops: a candidate whose images agree (the verifier's two-view stage passed) but of whose
epipolar inliers too few have a map point in both keyframes (``Verification.thin_map``) says
nothing against the place, only that the map is thin there (a real outdoor sequence: 117 of 122
candidates right, none accepted, e.g. 263 two-view inliers, 6 with map points). It is deferred
(``defer_retries``): after each of the next settled keyframes of its query's segment it is verified
again, as the same pair once either keyframe has gained map points, else as that newly settled
keyframe against the same match when it shares ``defer_min_shared_points`` map points with the
query (a later view of the place, as ORB-SLAM3 checks a candidate again in the next keyframes).
A verified retry goes on like any candidate (bridge rule, backend); its row in ``loops.csv`` then
shows the retried pair and the reason says "accepted after deferral (...)". A candidate is
otherwise "rejected after deferral", "superseded" (the detector proposed the same match for that
keyframe itself) or "gave up after N retries" (the budget, its segment or the stream ended).
Between two map segments that nothing joins yet (where short segments make thin maps), such a
candidate is first tried as a two-view join (``slam_backend.two_view_join``: rotation and
translation direction from the essential matrix, scale from each map's own points, as ORB-SLAM3
merges maps); the join then waits for support under the bridge rule like any loop between them.
Measured on gardens_point_day (12 segments): 13 such candidates, none accepted by retries alone
(settled keyframes and ended segments gain no map points), 8 by joins (3 of them on a retry), all
inside the GT loop band; before, 0 of 63 candidates were accepted. The synthetic demo is unchanged.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import gtsam
import networkx as nx
import numpy as np

from frontends.base import PointObservations, TrackResult
from frontends.errors import ConfigError
from frontends.mono_vo.masking import iou
from frontends.types import CameraIntrinsics, DetectedObject, Frame, Keyframe
from lcd.base import LoopCandidate, LoopDetector, ObjectDetector
from lcd.objects.filtering import MOVABLE_LABELS, VEHICLE_LABELS
from slam_backend.global_ba import (
    AdjustedMap,
    GlobalBundleAdjustmentConfig,
    LoopCorrespondences,
    global_bundle_adjustment,
    repose_frame,
)
from slam_backend.lie import as_4x4, pose_group, similarity_scale
from slam_backend.pcm import LoopMeasurement, OdometryChain, PairwiseConsistency
from slam_backend.posegraph import LoopDecision, PoseGraphBackend
from slam_backend.two_view_join import TwoViewJoinConfig, two_view_join
from slam_backend.verify import Verification, Verifier, colmap_camera

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LoopClosingConfig:
    #: Candidates (best first) verified per query keyframe.
    max_verifications: int = 2
    #: Verify candidates sharing defer_min_shared_points with a better one that failed on the maps alone
    verify_covisible_candidates: bool = False
    #: Verify candidates scoring this share of the detector's threshold, unless it has a proposal_threshold.
    proposal_ratio: float = 0.5
    #: Rotation sigma (rad) of the loose step linking a new map segment to the previous keyframe.
    segment_link_rotation_sigma: float = 1.0
    #: Translation sigma (map units) of the segment link.
    segment_link_translation_sigma: float = 100.0
    #: Log-scale sigma of the segment link.
    segment_link_log_scale_sigma: float = 1.0
    #: Seconds of keyframes whose median speed sets the segment link's scale and length; 0: identity.
    segment_link_speed_window_s: float = 2.0
    #: Largest scale change of the new map by the speed link (docs/2026-12-06-config-evidence.md)
    segment_link_max_scale_change: float = 5.0
    #: Odometry rotation sigma (rad) of keyframes without a covariance (e.g. the replay frontend).
    default_rotation_sigma: float = 0.005
    #: Default odometry translation sigma (fraction of the step length).
    default_translation_sigma: float = 0.02
    #: Default odometry log-scale sigma.
    default_log_scale_sigma: float = 0.01
    #: Rotation sigma (rad) added to every odometry covariance (docs/2026-12-06-config-evidence.md)
    floor_rotation_sigma: float = 1e-4
    #: Translation floor (fraction of the keyframe's median map-point depth).
    floor_translation_sigma: float = 1e-3
    #: Log-scale floor.
    floor_log_scale_sigma: float = 1e-3
    #: Wall-clock budget (s) of one verification; past it: rejected (docs/2026-12-06-config-evidence.md)
    verify_timeout_s: float = 30.0
    #: Verify a keyframe's candidates on a thread while later frames track; decided at the next keyframe.
    overlap_verification: bool = True
    #: Hand the backend's estimates to a ``CorrectableFrontend`` after every accepted loop.
    correct_frontend: bool = True
    #: Classes a masking frontend keeps out of its map (the object filter's movable classes).
    movable_labels: tuple[str, ...] = MOVABLE_LABELS
    #: People and animals seen by keyframes this close in time (s) count where a keyframe saw none; 0: off.
    walking_memory_s: float = 0.5
    #: Consistent loops needed to join two map segments; 1: the first (docs/2026-12-06-config-evidence.md)
    bridge_support: int = 2
    #: Confidence of the chi2 test between loops that bridge two segments.
    bridge_confidence: float = 0.999
    #: Seconds between the queries of loops that support a bridge; 0: any (docs/2026-12-06-walking-people.md)
    bridge_min_interval_s: float = 0.0
    #: Settled keyframes after which a thin-map candidate is re-verified (see "Deferred loops"); 0: rejected.
    defer_retries: int = 3
    #: Map points a retry keyframe must share with the deferred query (docs/2026-12-06-config-evidence.md)
    defer_min_shared_points: int = 15
    #: Joining unjoined map segments from a thin-map loop's two-view geometry (``TwoViewJoinConfig``).
    two_view_join: TwoViewJoinConfig = field(default_factory=TwoViewJoinConfig)
    #: Newer keyframes a keyframe waits for before it is used; None: the frontend's ``keyframes_in_flux``.
    settle_keyframes: int | None = None
    #: Keep keyframe images after loop detection used them (0.9 MB per 640x480 colour keyframe, unbounded).
    keep_keyframe_images: bool = False
    #: Full bundle adjustment at the end of the stream if a loop was accepted (``slam_backend.global_ba``).
    global_ba: GlobalBundleAdjustmentConfig = field(default_factory=GlobalBundleAdjustmentConfig)

    def __post_init__(self) -> None:
        if self.settle_keyframes is not None and self.settle_keyframes < 0:
            raise ConfigError(f"loop_closing: settle_keyframes must be >= 0, got {self.settle_keyframes}")
        if not self.verify_timeout_s > 0:
            raise ConfigError(f"loop_closing: verify_timeout_s must be positive, got {self.verify_timeout_s}")
        if not self.segment_link_max_scale_change > 1:
            raise ConfigError(
                "loop_closing: segment_link_max_scale_change must be > 1, got "
                f"{self.segment_link_max_scale_change}"
            )
        if not self.segment_link_speed_window_s >= 0:
            raise ConfigError(
                "loop_closing: segment_link_speed_window_s must be >= 0 (0 links segments by identity), "
                f"got {self.segment_link_speed_window_s}"
            )
        if self.bridge_support < 1 or not 0.0 < self.bridge_confidence < 1.0:
            raise ConfigError("loop_closing: bridge_support must be >= 1 and bridge_confidence in (0, 1)")
        if not self.bridge_min_interval_s >= 0.0:
            raise ConfigError("loop_closing: bridge_min_interval_s must be >= 0")
        if self.walking_memory_s < 0:
            raise ConfigError(f"loop_closing: walking_memory_s must be >= 0, got {self.walking_memory_s}")
        if self.defer_retries < 0 or self.defer_min_shared_points < 1:
            raise ConfigError(
                "loop_closing: defer_retries must be >= 0 and defer_min_shared_points >= 1, got "
                f"{self.defer_retries} and {self.defer_min_shared_points}"
            )


@dataclass(frozen=True)
class LoopRecord:
    """One verified candidate and what became of it."""

    query: int
    match: int
    query_frame: int
    match_frame: int
    score: float
    verified: bool
    inliers: int
    accepted: bool
    reason: str
    scale: float = float("nan")
    loop_id: int | None = None
    #: The verified relative Sim(3) (the query keyframe's pose in the match keyframe's frame).
    relative: np.ndarray | None = field(default=None, repr=False, compare=False)
    #: Verifications that found the map too thin before this outcome (0: never deferred); a
    #: deferred candidate's row shows the pair that decided it (a retry may pose a later keyframe).
    deferrals: int = 0
    #: How a candidate whose map was too thin got its constraint, e.g. "after deferral (12 -> 2:
    #: ...; verified as 13 -> 2 at retry 1)" or "by two-view join (...)"; "" for the others.
    note: str = ""
    #: The constraint is a two-view join (``slam_backend.two_view_join``), not the verifier's Sim(3).
    two_view: bool = False


#: What ``PoseGraphBackend.add_loops`` takes per loop: match, query, relative Sim(3), covariance, info.
LoopInput = tuple[int, int, np.ndarray, np.ndarray, Mapping[str, Any] | None]


@dataclass(frozen=True, eq=False)  # identity: one held loop may support several new ones
class _HeldBridge:
    """A verified loop between two segments not joined yet, waiting for support."""

    record_index: int
    segments: frozenset[int]
    loop: LoopInput


@dataclass(eq=False)
class _Deferral:
    """A candidate whose images agree but whose map was too thin, waiting for a retry."""

    record_index: int
    query: int
    match: int
    segment: int
    score: float
    #: Why the first verification deferred it.
    reason: str
    #: Mapped keypoints of the query and the match when the pair was last verified: the same pair
    #: is verified again only once either has gained map points.
    mapped: tuple[int, int]
    retries: int = 0
    #: Verifications that found the map too thin (the first one included).
    thin: int = 1
    #: The last retry's outcome ("" before the first).
    last: str = ""


@dataclass(frozen=True)
class _Entry:
    """A verification on its way to the backend: a detector's candidate (``deferral`` None, a new
    record at ``record_index``) or the retry of a deferred one (updates its record)."""

    candidate: LoopCandidate
    verification: Verification
    record_index: int
    deferral: _Deferral | None = None
    #: How the two-view join made the constraint ("" when the verifier's Sim(3) did, or none).
    join: str = ""


@dataclass
class _Pending:
    """A keyframe's verifications (its own candidates, then retries of deferred ones) running on a
    worker thread; ``jobs`` are (query, match) snapshots taken when they were handed over."""

    keyframe: Keyframe
    chosen: list[LoopCandidate]
    #: (keyframe the retry verifies from, candidate, its deferral) per retry.
    retries: list[tuple[Keyframe, LoopCandidate, _Deferral]]
    #: Records of deferred candidates that changed without a retry.
    closed: list[int]
    jobs: list[tuple[Keyframe, Keyframe]]
    #: Per job as the worker finishes it: the verification or what the verifier raised, and seconds.
    results: list[Verification | Exception] = field(default_factory=list)
    seconds: list[float] = field(default_factory=list)
    #: Set when the worker could not start (an earlier one still running past its budget).
    busy: bool = False
    worker: threading.Thread | None = None
    #: ``verify_timeout_s``: how long a checkpoint waits for each job still running.
    budget: float = 30.0
    #: Per chosen candidate: (better candidate's position, map points their matches share) for each
    #: better one covisible with it; such a candidate is skipped once one of those failed on the maps.
    covisible: list[tuple[tuple[int, int], ...]] = field(default_factory=list)

    def run(self, verifier: Verifier) -> None:
        for position, (query, match) in enumerate(self.jobs):
            start = time.perf_counter()
            skip = self._skip(position)
            try:
                outcome: Verification | Exception = skip or verifier.verify(query, match)
            except Exception as exc:  # handed to the pipeline's plugin boundary
                outcome = exc
            self.seconds.append(time.perf_counter() - start)
            self.results.append(outcome)

    def _skip(self, position: int) -> Verification | None:
        """The rejection of a chosen candidate whose match is covisible with a better candidate's
        that failed on the maps alone (its images agree): the query's map meets nearly the same
        points there and fails the same way. On a drifted revisit that is every keyframe's second
        candidate, each at the cost of a whole verification (docs/2026-12-07-covisible-candidates.md)."""
        for better, shared in self.covisible[position] if position < len(self.covisible) else ():
            earlier = self.results[better]
            if not isinstance(earlier, Verification) or not (why := _maps_failed(earlier)):
                continue
            query, match = self.jobs[position]
            reason = f"shares {shared} map points with keyframe {earlier.match}, whose candidate {why}"
            return Verification(query.id, match.id, False, f"not verified: {reason}")
        return None

    def wait(self) -> bool:
        """Wait for the worker while each job answers within ``budget``; whether it is stuck."""
        while self.worker is not None and self.worker.is_alive():
            done = len(self.results)
            self.worker.join(self.budget)
            if self.worker.is_alive() and len(self.results) == done:
                return True
        return False

    def __getstate__(self) -> dict[str, Any]:
        # A checkpoint waits for the worker (a stuck job counts as timed out when decided), so a
        # resumed run decides from the same answers as an uninterrupted one.
        self.wait()
        return {**self.__dict__, "worker": None}


@dataclass(frozen=True)
class _ThinMap:
    """What the verifier tells of a candidate whose map was too thin: its two-view stage."""

    #: (K, 2) keypoint indices (query, match) of the epipolar inliers.
    inlier_pairs: np.ndarray
    #: match_from_query [R | t] (3x4, |t| = 1), None without a calibrated two-view fit.
    match_from_query: np.ndarray | None
    triangulation_angle_deg: float


@dataclass
class _PosedFrame:
    frame_index: int
    timestamp: float
    anchor: int
    #: The frame's camera-to-world pose in its anchor keyframe's camera frame.
    relative: np.ndarray
    #: The segment's next keyframe, the frame's pose in its camera frame (through the anchor's
    #: pose when that keyframe arrived) and the frame's share of the time between the two.
    next_anchor: tuple[int, np.ndarray, float] | None = None
    #: The map points it was posed from (kept for the global bundle adjustment).
    observations: PointObservations | None = None

    def pose(self, anchors: Mapping[int, np.ndarray]) -> np.ndarray:
        """Camera-to-world SE(3) pose given keyframe poses: the anchors' two estimates of the
        frame blended by time (rotation slerp, translation linear), so that what a keyframe step
        gains after the frames were tracked (local BA, loop corrections) reaches the frames
        between the two keyframes smoothly instead of as a jump at the next keyframe."""
        pose = as_4x4(anchors[self.anchor] @ self.relative)
        if self.next_anchor is None:
            return pose
        next_id, next_relative, w = self.next_anchor
        other = as_4x4(anchors[next_id] @ next_relative)
        blended = np.eye(4)
        blended[:3, :3] = gtsam.Rot3(pose[:3, :3]).slerp(w, gtsam.Rot3(other[:3, :3])).matrix()
        blended[:3, 3] = (1.0 - w) * pose[:3, 3] + w * other[:3, 3]
        return blended


@dataclass
class LoopClosingCounters:
    object_detector_failures: int = 0
    loop_detector_failures: int = 0
    verifier_failures: int = 0
    verifier_timeouts: int = 0
    seconds: dict[str, float] = field(default_factory=lambda: defaultdict(float))


def _sigma_covariance(rotation: float, translation: float, log_scale: float) -> np.ndarray:
    return np.diag(np.r_[np.full(3, rotation), np.full(3, translation), log_scale] ** 2)


def _backend_reason(decision: LoopDecision | None) -> str:
    """Why a verified loop is not in the graph ("" when it is)."""
    return "" if decision is None or decision.accepted else "rejected by the backend"


def _decided_reason(record: LoopRecord, decision: LoopDecision | None) -> str:
    """The backend's reason, saying how a candidate whose map was too thin got its constraint."""
    reason = _backend_reason(decision)
    return f"{reason or 'accepted'} {record.note}" if record.note else reason


def _thin_map(verification: Verification) -> _ThinMap | None:
    """The two-view stage of a candidate whose images agreed but whose map was too thin there
    (``Verification.thin_map``), None for any other outcome."""
    if not verification.thin_map:
        return None
    two_view = verification.two_view
    if two_view is None:
        return _ThinMap(np.zeros((0, 2), np.int64), None, 0.0)
    return _ThinMap(two_view.inlier_pairs, two_view.match_from_query, float(two_view.triangulation_angle_deg))


def _deferred_reason(deferral: _Deferral) -> str:
    return f"deferred: {deferral.reason}" + (f"; {deferral.last}" if deferral.last else "")


def _maps_failed(verification: Verification) -> str:
    """How a verification failed on the maps alone ("" if it did not): its images agree, but the
    two maps disagree there, or the map is thin there."""
    if verification.maps_disagree:
        return "found maps that disagree there"
    return "found the map thin there" if verification.thin_map else ""


def _shared_points(first: Keyframe, second: Keyframe) -> int:
    """Map points two keyframes of one segment both observe (0 without point ids)."""
    if first.point_ids is None or second.point_ids is None or first.segment != second.segment:
        return 0
    a, b = first.point_ids, second.point_ids
    return len(np.intersect1d(a[a >= 0], b[b >= 0]))


def _mapped(keyframe: Keyframe) -> int:
    """Keypoints with a map point (what the verifier's Sim(3) needs in both keyframes)."""
    points = keyframe.points3d
    return 0 if points is None else int(np.isfinite(points).all(axis=1).sum())


def _retries(count: int) -> str:
    return f"{count} {'retry' if count == 1 else 'retries'}"


class LoopClosing:
    """The loop-closing half of the SLAM pipeline (the frontend is the other half)."""

    def __init__(
        self,
        backend: PoseGraphBackend,
        detector: LoopDetector | None = None,
        objects: ObjectDetector | None = None,
        verifier: Verifier | None = None,
        config: LoopClosingConfig = LoopClosingConfig(),
        on_loop: Callable[[LoopRecord], None] | None = None,
        on_correction: Callable[[dict[int, np.ndarray]], None] | None = None,
        on_keyframe: Callable[[Keyframe, Any], None] | None = None,
        camera: CameraIntrinsics | None = None,
    ) -> None:
        """``detector``/``verifier`` None: odometry only (the pose graph holds just the chain).

        ``on_loop`` sees every verified candidate's record; ``on_correction`` gets the backend's
        keyframe estimates (camera-to-world Sim(3), by keyframe id) after every event that accepted
        a loop, so the frontend can move its map there and keep tracking in the corrected map;
        ``on_keyframe`` gets each keyframe as the detector saw it (with objects) and the detector's
        graph of it when the detector exposes one (``last_graph``, SymbioLCD2), e.g. for a viewer.
        ``camera``: the keypoints' camera, for the global bundle adjustment (None: none runs)."""
        self.backend = backend
        self.camera = camera
        self.detector = detector
        self.objects = objects
        self.verifier = verifier
        self.config = config
        self.on_loop = on_loop
        self.on_correction = on_correction
        self.on_keyframe = on_keyframe
        self.counters = LoopClosingCounters()
        #: See "Settling"; ``symbio run`` sets it from the frontend when the config leaves it open.
        self.settle_keyframes = config.settle_keyframes or 0
        #: Keyframes received but not settled yet (oldest first), and the newest keyframe received
        #: per segment (what frames are anchored to).
        self._unsettled: list[Keyframe] = []
        self._newest_received: dict[int, Keyframe] = {}
        self._keyframes: dict[int, Keyframe] = {}
        self._odometry_pose: dict[int, np.ndarray] = {}
        self._frames: dict[int, _PosedFrame] = {}
        #: Per segment, the frames posed since its newest keyframe (they wait for the next one).
        self._between: dict[int, list[int]] = {}
        self._latest_keyframe: dict[int, int] = {}
        self._segment_frame: dict[int, np.ndarray] = {}
        self._paths: dict[int, str | None] = {}
        self._records: list[LoopRecord] = []
        #: Detections of frames the frontend asked about (``movable_boxes``), reused for keyframes.
        self._detections: dict[int, tuple[DetectedObject, ...]] = {}
        #: Each keyframe's detected objects, by keyframe id (the verifier leaves out walking people).
        self._objects: dict[int, tuple[DetectedObject, ...]] = {}
        self._previous: Keyframe | None = None
        #: A verification that ran past its budget and has not returned yet.
        self._late_verification: threading.Thread | None = None
        #: The last keyframe's verifications, decided when the next keyframe settles or at the end.
        self._pending: _Pending | None = None
        #: Loops between segments held for support, the segment pairs joined by an accepted loop,
        #: and the odometry steps (with covariances) that PCM's test of held loops runs along.
        self._held: list[_HeldBridge] = []
        #: Candidates deferred because the map was too thin there (see "Deferred loops").
        self._deferred: list[_Deferral] = []
        self._joined = nx.Graph()  # segments, an edge per pair joined by an accepted loop
        self._steps: list[tuple[np.ndarray, np.ndarray]] = []
        self._chain_index: dict[int, int] = {}
        self._pcm = self._bridge_test()
        #: Keypoint pairs of every verified candidate, by (query, match) keyframe ids.
        self._correspondences: dict[tuple[int, int], np.ndarray] = {}
        #: The global bundle adjustment's map (None until ``finish`` ran one), and the frames it
        #: posed again (camera-to-world SE(3) by frame index).
        self.adjusted: AdjustedMap | None = None
        self._reposed: dict[int, np.ndarray] = {}
        #: Frames keep what they were posed from only when a global bundle adjustment can use it.
        ba = config.global_ba
        self._keeps_observations = ba.enabled and ba.repose_frames and camera is not None

    def _bridge_test(self) -> PairwiseConsistency:
        chain = OdometryChain(pose_group("sim3"))
        for step, covariance in self._steps:
            chain.append(chain.group.from_matrix(step), covariance)
        return PairwiseConsistency(chain, self.config.bridge_confidence, 1)

    def __getstate__(self) -> dict[str, Any]:
        # A verification still running past its budget lives in this process only: a restored run
        # (checkpoint) starts without it, as a new process would. The gtsam chain is rebuilt.
        return {**self.__dict__, "_late_verification": None, "_pcm": None}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._pcm = self._bridge_test()

    # -- input -------------------------------------------------------------------------------------

    def add(self, result: TrackResult, frame: Frame | None = None) -> list[LoopRecord]:
        """Take one frontend result (and the results it backfills); returns this call's loop records."""
        if frame is not None:
            self._paths[frame.index] = frame.path
        records: list[LoopRecord] = []
        # Keyframes first: frames a frontend posed before a new map's first keyframe (tracked
        # backwards from it) are anchored to it.
        for item in sorted(result.backfilled, key=lambda r: (r.keyframe is None, r.frame_index)):
            records += self._add_one(item)
        records += self._add_one(result)
        return records

    def finish(self) -> list[LoopRecord]:
        """Settle the keyframes still waiting (the stream ended), release the loop detector's
        database (its optional ``release()``), then run the global bundle adjustment if a loop was
        accepted; returns the loop records of the settled keyframes."""
        records: list[LoopRecord] = []
        while self._unsettled:
            records += self._add_keyframe(self._unsettled.pop(0))
        records += self._decide_pending()
        ended = [d.record_index for d in self._deferred]
        for d in list(self._deferred):
            self._records[d.record_index] = self._give_up(d, "the stream ended")
        records += self._report(ended)
        # No keyframe comes after this: the detector's database (most of a long run's memory) goes
        # before the bundle adjustment needs its own (docs/2026-12-06-long-runs.md).
        release = getattr(self.detector, "release", None)
        if callable(release):
            release()
        _return_freed_memory()
        self._global_bundle_adjustment()
        _return_freed_memory()
        return records

    def _global_bundle_adjustment(self) -> None:
        config = self.config.global_ba
        accepted = [
            LoopCorrespondences(r.query, r.match, self._correspondences[(r.query, r.match)])
            for r in self.loops()
            if r.accepted and (r.query, r.match) in self._correspondences
        ]
        if not config.enabled or self.camera is None or not accepted:
            return
        start = time.perf_counter()
        estimates = self.backend.estimate()
        # As ORB-SLAM3 adjusts the map a loop closed in: segments no accepted loop reaches (joined to
        # the others only by segment links) have nothing to gain, and their own local BA used
        # every point, where the global one thins them (docs/2026-12-06-long-runs.md).
        looped = {self._keyframes[k].segment for loop in accepted for k in (loop.query, loop.match)}
        self.adjusted = global_bundle_adjustment(
            [kf for kf in self._keyframes.values() if kf.segment in looped], estimates, accepted, self.camera,
            config,
        )  # fmt: skip
        self.counters.seconds["global_ba"] += time.perf_counter() - start
        if self.adjusted is None:
            return
        if config.repose_frames:
            start = time.perf_counter()
            self._repose_frames(self.adjusted, looped)
            self.counters.seconds["repose_frames"] += time.perf_counter() - start
        s = self.adjusted.stats
        log.info(
            "global bundle adjustment: %d keyframes, %d points, %d observations (%d from loops, "
            "%d fused), median reprojection error %.2f -> %.2f px; %d of %d frames posed again",
            s.keyframes, s.points, s.observations, s.loop_observations, s.fused_observations,
            s.median_error_before_px, s.median_error_after_px, self.frames_reposed, len(self._frames),
        )  # fmt: skip

    def _repose_frames(self, adjusted: AdjustedMap, segments: set[int]) -> None:
        """Pose the frames of the adjusted ``segments`` again against the adjusted points, on every
        core: pycolmap's refinement releases the GIL, and each frame is independent (9000-frame
        figure 8: 12 s on one core; docs/2026-12-07-global-ba-memory.md)."""
        assert self.camera is not None
        camera = colmap_camera(self.camera)
        adjusted.positions(0, np.zeros(0, np.int64))  # build the shared point lookup once, up front
        work = []
        for index, posed in self._frames.items():
            segment = self._keyframes[posed.anchor].segment
            if posed.observations is None or posed.anchor in adjusted.followers or segment not in segments:
                continue
            work.append((index, segment, posed.observations, posed.pose(adjusted.poses)))

        def repose(item: tuple[int, int, PointObservations, np.ndarray]) -> np.ndarray | None:
            _, segment, observations, initial = item
            return repose_frame(adjusted, segment, observations, initial, camera, self.config.global_ba)

        with ThreadPoolExecutor(max(1, min(len(work), os.cpu_count() or 1)), "repose") as pool:
            for (index, *_), pose in zip(work, pool.map(repose, work, chunksize=64), strict=True):
                if pose is not None:
                    self._reposed[index] = pose

    def _add_one(self, result: TrackResult) -> list[LoopRecord]:
        records = []
        keyframe = result.keyframe
        if keyframe is not None and not self._received(keyframe.id):
            records = self._receive(keyframe)
        if result.pose is not None:
            anchor = self._newest_received.get(result.segment)
            if anchor is None:  # no keyframe in this segment yet: nothing to anchor to
                return records
            # A keyframe's own frame is the keyframe: the frontend's tracking estimate of it is
            # older than the keyframe's bundle-adjusted pose (2-3 cm apart on the synthetic loops).
            own = keyframe is not None and keyframe.id == anchor.id
            relative = np.eye(4) if own else np.linalg.inv(anchor.pose) @ result.pose
            self._frames[result.frame_index] = _PosedFrame(
                result.frame_index, result.timestamp, anchor.id, relative,
                observations=None if own or not self._keeps_observations else self._kept(result.observations),
            )  # fmt: skip
            if not own:
                self._between.setdefault(result.segment, []).append(result.frame_index)
        return records

    def _kept(self, observations: PointObservations | None) -> PointObservations | None:
        """What a frame keeps of its observations for re-posing: ids as int32 and, if set, at most
        ``frame_max_observations`` (evenly spaced). Kept for every frame of the run: ~900
        observations took 14 kB per frame (docs/2026-12-06-long-runs.md)."""
        if observations is None:
            return None
        keypoints, ids = observations.keypoints, observations.point_ids
        cap = self.config.global_ba.frame_max_observations
        if 0 < cap < len(ids):
            chosen = np.linspace(0, len(ids) - 1, cap).round().astype(np.int64)
            keypoints, ids = keypoints[chosen], ids[chosen]
        if len(ids) == 0 or int(ids.max()) < np.iinfo(np.int32).max:
            ids = ids.astype(np.int32)
        return PointObservations(np.asarray(keypoints, dtype=np.float32), ids)

    def _link_frames(self, keyframe: Keyframe) -> None:
        """Give the frames posed since the segment's previous keyframe their second anchor."""
        previous = self._newest_received.get(keyframe.segment)
        waiting = self._between.pop(keyframe.segment, [])
        if previous is None:
            return
        through = np.linalg.inv(keyframe.pose) @ previous.pose
        span = keyframe.timestamp - previous.timestamp
        for index in waiting:
            posed = self._frames[index]
            share = (posed.timestamp - previous.timestamp) / span if span > 0 else 1.0
            posed.next_anchor = (keyframe.id, through @ posed.relative, float(np.clip(share, 0.0, 1.0)))

    def _received(self, keyframe_id: int) -> bool:
        return keyframe_id in self._keyframes or any(k.id == keyframe_id for k in self._unsettled)

    def _receive(self, keyframe: Keyframe) -> list[LoopRecord]:
        """Queue a new keyframe; settle those with ``settle_keyframes`` newer ones (or whose
        segment ended)."""
        records: list[LoopRecord] = []
        while self._unsettled and self._unsettled[0].segment != keyframe.segment:
            records += self._add_keyframe(self._unsettled.pop(0))
        self._unsettled.append(keyframe)
        self._link_frames(keyframe)
        self._newest_received[keyframe.segment] = keyframe
        while self._unsettled and len(self._unsettled) > self._settle_count(self._unsettled[0]):
            records += self._add_keyframe(self._unsettled.pop(0))
        return records

    def _settle_count(self, keyframe: Keyframe) -> int:
        """Newer keyframes ``keyframe`` waits for: ``settle_keyframes``, and at least one when it
        starts a new map segment (the link to the old segment needs the new one's speed)."""
        restarts = self._previous is not None and keyframe.segment != self._previous.segment
        return max(self.settle_keyframes, int(restarts))

    def _add_keyframe(self, keyframe: Keyframe) -> list[LoopRecord]:
        start = time.perf_counter()
        self.adjusted, self._reposed = None, {}  # the stream goes on: the graph is the answer again
        previous = self._previous
        if previous is None:
            step, covariance = keyframe.pose.copy(), _sigma_covariance(1e-3, 1e-3, 1e-3)
        elif previous.segment != keyframe.segment:
            c = self.config
            step = self._segment_link(previous, keyframe)
            covariance = _sigma_covariance(
                c.segment_link_rotation_sigma,
                c.segment_link_translation_sigma,
                c.segment_link_log_scale_sigma,
            )
        else:
            step = np.linalg.inv(previous.pose) @ keyframe.pose
            covariance = (
                keyframe.odometry_covariance
                if keyframe.odometry_covariance is not None
                else self._default_covariance(step)
            ) + self._floor(keyframe)
        self.backend.add_keyframe(keyframe.id, step, covariance)
        self._steps.append((step, covariance))
        self._pcm.chain.append(self._pcm.group.from_matrix(step), covariance)
        self._chain_index[keyframe.id] = len(self._steps) - 1
        self._odometry_pose[keyframe.id] = (
            step if previous is None else self._odometry_pose[previous.id] @ step
        )
        self._keyframes[keyframe.id] = keyframe
        if keyframe.segment not in self._latest_keyframe:
            # Graph frame <- this segment's map frame: what corrections are converted back with.
            self._segment_frame[keyframe.segment] = self._odometry_pose[keyframe.id] @ np.linalg.inv(
                keyframe.pose
            )
        self._latest_keyframe[keyframe.segment] = keyframe.id
        self._previous = keyframe
        self.counters.seconds["backend"] += time.perf_counter() - start
        try:
            if self.detector is None:
                return []
            return self._close_loops(self._with_objects(keyframe))
        finally:
            # The object and loop detectors (and the viewer) are done with the image. The frontend,
            # the run's results and this pipeline share this keyframe object, so one release frees
            # it for all (docs/slam-runs.md, "Long runs").
            if not self.config.keep_keyframe_images:
                keyframe.image = None

    def _segment_link(self, previous: Keyframe, first: Keyframe) -> np.ndarray:
        """Sim(3) step from the old segment's last keyframe to the new segment's first at constant
        velocity (module docstring); identity when either segment has no speed to go by."""
        window = self.config.segment_link_speed_window_s
        if window <= 0:
            return np.eye(4)
        old = [
            (k.timestamp, self._odometry_pose[k.id][:3, 3])
            for k in self._keyframes.values()
            if k.segment == previous.segment and k.timestamp >= previous.timestamp - window
        ]
        new = [
            (k.timestamp, k.pose[:3, 3])
            for k in [first, *self._unsettled]
            if k.segment == first.segment and k.timestamp <= first.timestamp + window
        ]
        old_velocity, new_velocity = _recent_velocity(old), _recent_velocity(new)
        if old_velocity is None or new_velocity is None:
            return np.eye(4)
        old_speed, new_speed = old_velocity[0], new_velocity[0]
        previous_pose = self._odometry_pose[previous.id]
        # Keep the orientation, move on at the old velocity, and take the new map's units to the old
        # speed (the new keyframe's own scale stays as its later steps assume).
        scale = old_speed / new_speed * similarity_scale(first.pose)
        change = scale / similarity_scale(previous_pose)  # against the identity link
        log.info(
            "segment %d -> %d: speeds %.4g and %.4g units/s, scale %.3g x the identity link's",
            previous.segment, first.segment, old_speed, new_speed, change,
        )  # fmt: skip
        if abs(np.log(change)) > np.log(self.config.segment_link_max_scale_change):
            # One of the two maps' scales ran away (a collapsing map is what loses tracking): the
            # new map's own initialisation, tied to the scene's depth, is the better unit.
            return np.eye(4)
        target = as_4x4(previous_pose)
        target[:3, :3] *= scale
        target[:3, 3] += old_velocity[1] * old_speed * (first.timestamp - previous.timestamp)
        return np.linalg.inv(previous_pose) @ target

    def _floor(self, keyframe: Keyframe) -> np.ndarray:
        c = self.config
        depth = 1.0
        if keyframe.points3d is not None:
            depths = keyframe.points3d[:, 2]
            depths = depths[np.isfinite(depths) & (depths > 0)]
            if len(depths):
                depth = float(np.median(depths))
        return _sigma_covariance(
            c.floor_rotation_sigma, c.floor_translation_sigma * depth, c.floor_log_scale_sigma
        )

    def _default_covariance(self, step: np.ndarray) -> np.ndarray:
        c = self.config
        length = max(float(np.linalg.norm(step[:3, 3])), 1e-6)
        return _sigma_covariance(
            c.default_rotation_sigma, c.default_translation_sigma * length, c.default_log_scale_sigma
        )

    def _detect(self, frame: Frame) -> tuple[DetectedObject, ...]:
        """The object detector's objects in ``frame`` (computed once per frame)."""
        if frame.index in self._detections:
            return self._detections.pop(frame.index)
        assert self.objects is not None
        start = time.perf_counter()
        try:
            found = tuple(self.objects.detect(frame.image, frame))
        except Exception as exc:  # plugin boundary: a failing detector costs this frame its objects
            self.counters.object_detector_failures += 1
            log.warning("object detector %s failed on frame %d: %r", self.objects.name, frame.index, exc)
            found = ()
        self.counters.seconds["objects"] += time.perf_counter() - start
        return found

    def movable_boxes(self, frame: Frame) -> list[tuple[float, float, float, float, float]]:
        """Boxes of the objects in ``frame`` that can move on their own (``movable_labels``), for a
        frontend that keeps them out of its map; the detections are kept for the keyframe. A fifth
        value 1 marks a vehicle, which is often parked: the frontend may keep it when it sees it
        static. People and animals (0) stand still only for moments, and two views cannot see one
        walking along the camera's path (docs/2026-12-06-masking.md), so they stay masked."""
        if self.objects is None:
            return []
        found = self._detect(frame)
        self._detections[frame.index] = found
        movable = set(self.config.movable_labels)
        return [(*o.box, float(o.label in VEHICLE_LABELS)) for o in found if o.label in movable]

    def _with_objects(self, keyframe: Keyframe) -> Keyframe:
        if self.objects is None or keyframe.image is None:
            return keyframe
        path = self._paths.get(keyframe.frame_index)
        found = self._detect(Frame(keyframe.frame_index, keyframe.timestamp, keyframe.image, path))
        # Labels and boxes only: a segmenting detector's masks would grow with every keyframe.
        self._keyframe_objects()[keyframe.id] = tuple(replace(o, mask=None) for o in found)
        # The frontend's keyframe object stays the frontend's; the detector gets a copy with objects.
        return replace(keyframe, objects=found)

    def _job_copy(self, keyframe: Keyframe) -> Keyframe:
        """A shallow copy of ``keyframe`` for the verifier, with its detected objects and the people
        and animals its neighbours saw where it saw none (``_walking_missed``)."""
        objects = keyframe.objects or self._keyframe_objects().get(keyframe.id, ())
        return replace(keyframe, objects=(*objects, *self._walking_missed(keyframe, objects)))

    def _walking_missed(self, keyframe: Keyframe, own: tuple[DetectedObject, ...]) -> list[DetectedObject]:
        """People and animals the keyframes up to ``walking_memory_s`` away saw where ``keyframe``'s
        own detections (``own``) have none. A detector misses some views of a person, and a person
        who walked through both views of a loop joins them wrongly (docs/2026-12-06-walking-people.md);
        one in view a moment before and after is likely in view between. Keyframes of another map
        segment count too: the first keyframe of a new segment has no neighbour of its own before it,
        and a wrong join there was a person the previous segment's last keyframe saw
        (docs/2026-12-07-backend-cost.md). A person the keyframe saw itself is where its own box says."""
        window = self.config.walking_memory_s
        if window <= 0:
            return []
        labels = set(self.config.movable_labels) - set(VEHICLE_LABELS)
        seen_here = [o.box for o in own if o.label in labels]
        objects, found = self._keyframe_objects(), []
        # Keyframes not settled yet: their detections wait in _detections, by frame.
        unsettled = {k.id: k for k in self._unsettled}
        for step in (-1, 1):
            kf_id = keyframe.id + step
            while (other := self._keyframes.get(kf_id) or unsettled.get(kf_id)) is not None and abs(
                other.timestamp - keyframe.timestamp
            ) <= window:
                seen = objects.get(other.id, self._detections.get(other.frame_index, ()))
                found += [o for o in seen if o.label in labels and all(iou(o.box, b) == 0 for b in seen_here)]
                kf_id += step
        return found

    def _keyframe_objects(self) -> dict[int, tuple[DetectedObject, ...]]:
        """``_objects``, made empty when resuming a checkpoint from before it existed."""
        if not hasattr(self, "_objects"):
            self._objects = {}
        return self._objects

    def _close_loops(self, keyframe: Keyframe) -> list[LoopRecord]:
        assert self.detector is not None
        start = time.perf_counter()
        try:
            candidates = self.detector.add(keyframe)
        except Exception as exc:  # plugin boundary, like the object detector
            self.counters.loop_detector_failures += 1
            log.warning("loop detector %s failed on keyframe %d: %r", self.detector.name, keyframe.id, exc)
            candidates = []
        self.counters.seconds["loop_detector"] += time.perf_counter() - start
        if self.on_keyframe is not None:
            self.on_keyframe(keyframe, getattr(self.detector, "last_graph", None))
        chosen = [c for c in candidates if self._proposed(c.score) and c.match in self._keyframes]
        chosen = chosen[: self.config.max_verifications]
        # The previous keyframe's verifications are decided first: its loops change what the
        # retries below see (deferred candidates, joined segments), as in a run without overlap.
        records = self._decide_pending()
        retries, closed = self._retry_deferred(keyframe, {c.match for c in chosen})
        self._pending = self._start_verifications(keyframe, chosen, retries, closed)
        if not self.config.overlap_verification:
            records += self._decide_pending()
        return records

    def _start_verifications(
        self,
        keyframe: Keyframe,
        chosen: list[LoopCandidate],
        retries: list[tuple[Keyframe, LoopCandidate, _Deferral]],
        closed: list[int],
    ) -> _Pending:
        """Hand the keyframe's verifications to a worker thread (``_Pending``)."""
        # Shallow copies: the frontend re-assigns a keyframe's pose and points while the worker reads.
        jobs = [(self._job_copy(keyframe), self._job_copy(self._keyframes[c.match])) for c in chosen]
        jobs += [(self._job_copy(query), self._job_copy(self._keyframes[c.match])) for query, c, _ in retries]
        pending = _Pending(keyframe, chosen, retries, closed, jobs, budget=self.config.verify_timeout_s)
        if not self.config.verify_covisible_candidates:
            pending.covisible = self._covisible_candidates(chosen)
        if not jobs or self.verifier is None:
            return pending
        late = self._late_verification
        if late is not None:
            late.join(self.config.verify_timeout_s)
            if late.is_alive():
                pending.busy = True
                return pending
            self._late_verification = None
        # A daemon thread: a verifier that never returns cannot keep the process alive at exit.
        pending.worker = threading.Thread(
            target=pending.run, args=(self.verifier,), name=f"verify keyframe {keyframe.id}", daemon=True
        )
        pending.worker.start()
        return pending

    def _covisible_candidates(self, chosen: list[LoopCandidate]) -> list[tuple[tuple[int, int], ...]]:
        """Per chosen candidate, the better ones whose match shares at least
        ``defer_min_shared_points`` map points with its match: (position, shared points)."""
        matches = [self._keyframes[c.match] for c in chosen]
        covisible = []
        for position, match in enumerate(matches):
            shared = ((k, _shared_points(better, match)) for k, better in enumerate(matches[:position]))
            covisible.append(tuple((k, n) for k, n in shared if n >= self.config.defer_min_shared_points))
        return covisible

    def _pending_verifications(self, pending: _Pending) -> list[Verification]:
        """Wait for the worker (each job within ``verify_timeout_s``) and turn its answers into
        verifications: a raise or a late answer rejects that candidate only."""
        budget = pending.budget
        if pending.wait():
            self._late_verification = pending.worker  # no answer within the budget
        self.counters.seconds["verifier"] += sum(pending.seconds)
        verifications = []
        for position, (query, match) in enumerate(pending.jobs):
            if self.verifier is None:
                verifications.append(Verification(query.id, match.id, False, "no verifier"))
            elif pending.busy:
                why = "the verifier is still busy with an earlier candidate"
                verifications.append(self._timed_out(query.id, match.id, why))
            elif position >= len(pending.results) or pending.seconds[position] > budget:
                verifications.append(self._timed_out(query.id, match.id, f"no answer within {budget:g} s"))
            elif isinstance(pending.results[position], Exception):
                exc = pending.results[position]
                self.counters.verifier_failures += 1
                log.warning("verifier %s failed on %d -> %d: %r", self.verifier.name, query.id, match.id, exc)
                verifications.append(Verification(query.id, match.id, False, f"verifier error: {exc!r}"))
            else:
                verifications.append(pending.results[position])  # type: ignore[arg-type]
        return verifications

    def _decide_pending(self) -> list[LoopRecord]:
        """Decide the pending keyframe's verified candidates: two-view joins, the backend, records."""
        pending, self._pending = self._pending, None
        if pending is None:
            return []
        keyframe = pending.keyframe
        verifications = self._pending_verifications(pending)
        own, later = verifications[: len(pending.chosen)], verifications[len(pending.chosen) :]
        # The detector's candidates get new records; retries of deferred ones update theirs.
        entries: list[_Entry] = [
            _Entry(c, v, len(self._records) + i)
            for i, (c, v) in enumerate(zip(pending.chosen, own, strict=True))
        ]
        retries = [
            _Entry(c, v, d.record_index, d) for (_, c, d), v in zip(pending.retries, later, strict=True)
        ]
        closed = pending.closed
        entries = [self._join(entry) for entry in entries + retries]
        if not entries:
            return self._report(closed)
        for entry in entries:
            v = entry.verification
            if v.verified and v.correspondences is not None:
                self._correspondences[(v.query, v.match)] = v.correspondences
        start = time.perf_counter()
        loops: list[LoopInput] = []
        positions = []  # of the verified candidates, in the order they go to the backend
        held: dict[int, tuple[frozenset[int], LoopInput]] = {}  # position -> segments, loop
        released: list[_HeldBridge] = []
        for position, entry in enumerate(entries):
            c, v = entry.candidate, entry.verification
            if v.verified and v.relative is not None and v.covariance is not None:
                info = {"score": float(c.score), "inliers": v.inliers}
                loop = (c.match, c.query, v.relative, v.covariance, info)
                segments = self._segments(loop)
                if len(segments) == 2 and not self._connected(segments):
                    support = self._support(segments, loop)
                    if len(support) + 1 < self.config.bridge_support:
                        held[position] = (segments, loop)
                        continue
                    released += [h for h in support if all(h is not r for r in released)]
                loops.append(loop)
                positions.append(position)
        sent = loops + [h.loop for h in released]
        outcome = self.backend.add_loops(sent) if sent else []
        decisions = dict(zip(positions, outcome[: len(loops)], strict=True))
        for bridge, bridge_decision in zip(released, outcome[len(loops) :], strict=True):
            self._held.remove(bridge)
            bridge_record = self._records[bridge.record_index]
            self._records[bridge.record_index] = replace(
                bridge_record,
                accepted=bridge_decision.accepted,
                reason=_decided_reason(bridge_record, bridge_decision),
                loop_id=bridge_decision.loop_id,
            )
        for sent_loop, loop_decision in zip(sent, outcome, strict=True):
            if loop_decision.accepted and len(self._segments(sent_loop)) == 2:
                self._joined.add_edge(*self._segments(sent_loop))
        self.counters.seconds["backend"] += time.perf_counter() - start
        fresh: list[LoopRecord] = []
        for position, entry in enumerate(entries):
            record = self._entry_record(entry, decisions.get(position))
            if position in held:
                held_segments, held_loop = held[position]
                self._held.append(_HeldBridge(entry.record_index, held_segments, held_loop))
                first, second = sorted(held_segments)
                reason = (
                    f"held: joins map segments {first} and {second}; waits for "
                    f"{self.config.bridge_support - 1} more consistent loop(s) between them"
                )
                record = replace(record, reason=f"{reason}; {record.note}" if record.note else reason)
            if entry.deferral is None:
                fresh.append(record)
            else:
                self._records[entry.record_index] = record
                closed.append(entry.record_index)
        self._records += fresh
        records = [*fresh, *self._report(closed)]
        if self.on_loop is not None:
            for record in fresh:
                self.on_loop(record)
        if self.on_correction is not None and any(d.accepted for d in outcome):
            self.on_correction(self._current_segment_estimates(keyframe.segment))
        return records

    def _proposed(self, score: float) -> bool:
        """Whether a candidate's score is worth a geometric check (docs/2026-12-06-config-evidence.md)."""
        assert self.detector is not None
        floor = getattr(self.detector, "proposal_threshold", None)
        if floor is None:
            floor = self.config.proposal_ratio * self.detector.threshold
        return score >= floor and score > 0

    def _entry_record(self, entry: _Entry, decision: LoopDecision | None) -> LoopRecord:
        """The record of a verified candidate or retry; defers a fresh candidate on a thin map."""
        c, v, d = entry.candidate, entry.verification, entry.deferral
        thin = not v.verified and _thin_map(v) is not None
        if d is None:
            deferred = thin and self.config.defer_retries > 0
            if deferred:
                query, match = self._keyframes[c.query], self._keyframes[c.match]
                self._deferred.append(
                    _Deferral(
                        entry.record_index, c.query, c.match, query.segment, float(c.score), v.reason,
                        (_mapped(query), _mapped(match)),
                    )
                )  # fmt: skip
            record = self._new_record(c, v, decision, int(deferred), entry.join, two_view=bool(entry.join))
            reason = f"deferred: {v.reason}" if deferred else v.reason or _decided_reason(record, decision)
            return replace(record, reason=reason)
        record = self._records[entry.record_index]
        attempt = f"retry {d.retries} ({c.query} -> {c.match})"
        if thin:
            d.thin += 1
            d.last = f"{attempt}: {v.reason}"
            if d.retries < self.config.defer_retries:
                return replace(record, reason=_deferred_reason(d), deferrals=d.thin)
            return self._give_up(d, "the map stayed too thin there")
        self._deferred.remove(d)
        if not v.verified:
            reason = f"rejected after deferral: {v.reason} ({attempt}; deferred: {d.reason})"
            return replace(record, reason=reason, deferrals=d.thin)
        how = "joined" if entry.join else "verified"
        note = (
            f"after deferral ({d.query} -> {d.match}: {d.reason}; {how} as {c.query} -> {c.match} "
            f"at retry {d.retries})" + (f" {entry.join}" if entry.join else "")
        )
        verified = self._new_record(c, v, decision, d.thin, note, two_view=bool(entry.join))
        return replace(verified, reason=_decided_reason(verified, decision))

    def _new_record(
        self,
        candidate: LoopCandidate,
        verification: Verification,
        decision: LoopDecision | None,
        deferrals: int = 0,
        note: str = "",
        two_view: bool = False,
    ) -> LoopRecord:
        """The record with an empty reason (the caller sets it)."""
        return LoopRecord(
            candidate.query,
            candidate.match,
            self._keyframes[candidate.query].frame_index,
            self._keyframes[candidate.match].frame_index,
            float(candidate.score),
            verification.verified,
            verification.inliers,
            decision is not None and decision.accepted,
            "",
            verification.scale,
            decision.loop_id if decision is not None else None,
            verification.relative,
            deferrals,
            note,
            two_view,
        )

    def _join(self, entry: _Entry) -> _Entry:
        """A thin-map candidate between two segments that nothing joins yet, with the two-view
        join's constraint when there is one (else its reason says why there is none)."""
        c, v = entry.candidate, entry.verification
        thin = _thin_map(v)
        config = self.config.two_view_join
        if v.verified or thin is None or not config.enabled or self.camera is None:
            return entry
        query, match = self._keyframes[c.query], self._keyframes[c.match]
        segments = frozenset((query.segment, match.segment))
        if len(segments) < 2 or self._connected(segments):
            return entry
        join = two_view_join(
            query,
            match,
            thin.inlier_pairs,
            thin.match_from_query,
            thin.triangulation_angle_deg,
            self.camera,
            config,
        )
        if isinstance(join, str):
            return replace(entry, verification=replace(v, reason=f"{v.reason}; no two-view join: {join}"))
        note = (
            f"by two-view join ({v.inliers} epipolar inliers, {thin.triangulation_angle_deg:.1f} deg, "
            f"scale from {join.points[0]} + {join.points[1]} map points)"
        )
        joined = Verification(
            v.query,
            v.match,
            True,
            "",
            v.matches,
            v.inliers,
            join.relative,
            join.covariance,
            join.correspondences,
        )
        return replace(entry, verification=joined, join=note)

    def _retry_deferred(
        self, keyframe: Keyframe, proposed: set[int]
    ) -> tuple[list[tuple[Keyframe, LoopCandidate, _Deferral]], list[int]]:
        """The retries of deferred candidates now that ``keyframe`` settled ("Deferred loops"),
        and the records of those that changed without one; ``proposed``: the matches the detector
        proposed for ``keyframe`` itself."""
        retries: list[tuple[Keyframe, LoopCandidate, _Deferral]] = []
        closed: list[int] = []
        for d in list(self._deferred):
            closed.append(d.record_index)
            if d.segment != keyframe.segment:
                self._records[d.record_index] = self._give_up(d, f"map segment {d.segment} ended")
                continue
            if d.match in proposed:  # already verified as the keyframe's own candidate
                self._deferred.remove(d)
                reason = f"superseded by candidate {keyframe.id} -> {d.match}; {_deferred_reason(d)}"
                self._records[d.record_index] = replace(self._records[d.record_index], reason=reason)
                continue
            d.retries += 1
            query, match = self._keyframes[d.query], self._keyframes[d.match]
            mapped = (_mapped(query), _mapped(match))
            shared = _shared_points(keyframe, query)
            if mapped[0] > d.mapped[0] or mapped[1] > d.mapped[1]:
                # The frontend refreshed either keyframe with new map points: the same pair again.
                d.mapped, chosen = mapped, query
            elif shared >= min(self.config.defer_min_shared_points, mapped[0] // 2):
                chosen = keyframe  # a later view of the same place, with its own map points
            else:
                d.last = (
                    f"retry {d.retries} skipped: keyframe {keyframe.id} shares {shared} map points "
                    f"with {d.query}"
                )
                self._records[d.record_index] = (
                    self._give_up(d, "the query's segment left the place")
                    if d.retries >= self.config.defer_retries
                    else replace(self._records[d.record_index], reason=_deferred_reason(d))
                )
                continue
            closed.pop()  # its record changes with the retry's outcome
            candidate = LoopCandidate(chosen.id, d.match, d.score, {})
            retries.append((chosen, candidate, d))
        return retries, closed

    def _give_up(self, deferral: _Deferral, why: str) -> LoopRecord:
        """Drop a deferred candidate; its record with the reason."""
        self._deferred.remove(deferral)
        reason = f"gave up after {_retries(deferral.retries)}: {why}; {_deferred_reason(deferral)}"
        return replace(self._records[deferral.record_index], reason=reason, deferrals=deferral.thin)

    def _report(self, indices: list[int]) -> list[LoopRecord]:
        """The records at ``indices`` (changed by this keyframe), also to ``on_loop``."""
        records = [self._records[i] for i in indices]
        if self.on_loop is not None:
            for record in records:
                self.on_loop(record)
        return records

    def _segments(self, loop: LoopInput) -> frozenset[int]:
        return frozenset((self._keyframes[loop[0]].segment, self._keyframes[loop[1]].segment))

    def _connected(self, segments: frozenset[int]) -> bool:
        """Whether accepted loops join the two segments (directly or through others)."""
        first, second = sorted(segments)
        joined = self._joined
        return first in joined and second in joined and nx.has_path(joined, first, second)

    def _support(self, segments: frozenset[int], loop: LoopInput) -> list[_HeldBridge]:
        """The held loops between ``segments`` that pass PCM's pairwise test with ``loop`` and are
        another look: other keyframes on both sides, queries ``bridge_min_interval_s`` apart. One
        view verified twice is one piece of evidence, and a person walking through both views of
        the place keeps a wrong two-view pose for a moment (docs/2026-12-06-walking-people.md)."""
        new = self._measurement(loop)
        match, query = loop[0], loop[1]
        when = self._keyframes[query].timestamp
        return [
            h
            for h in self._held
            if h.segments == segments
            and h.loop[0] != match
            and h.loop[1] != query
            and abs(self._keyframes[h.loop[1]].timestamp - when) >= self.config.bridge_min_interval_s
            and self._pcm.mahalanobis(new, self._measurement(h.loop)) < self._pcm.threshold
        ]

    def _measurement(self, loop: LoopInput) -> LoopMeasurement:
        match, query, relative, covariance, _ = loop
        return LoopMeasurement(
            self._chain_index[match],
            self._chain_index[query],
            self._pcm.group.from_matrix(relative),
            covariance,
        )

    def _current_segment_estimates(self, segment: int) -> dict[int, np.ndarray]:
        """The backend's estimates of the keyframes of ``segment``, in that segment's map frame."""
        to_segment = np.linalg.inv(self._segment_frame[segment])
        estimates = self._sim3_estimates()
        return {k: to_segment @ estimates[k] for k, kf in self._keyframes.items() if kf.segment == segment}

    def _timed_out(self, query: int, match: int, why: str) -> Verification:
        self.counters.verifier_timeouts += 1
        log.warning("verifier timeout on %d -> %d: %s; candidate rejected", query, match, why)
        return Verification(query, match, False, f"timeout: {why}")

    # -- output ------------------------------------------------------------------------------------

    def loops(self) -> list[LoopRecord]:
        """Every verified candidate with the backend's current decision (PCM may revise earlier ones)."""
        decisions = self.backend.decisions()
        return [
            replace(
                r, accepted=decisions[r.loop_id].accepted, reason=_decided_reason(r, decisions[r.loop_id])
            )
            if r.loop_id is not None
            else r
            for r in self._records
        ]

    @property
    def frames_reposed(self) -> int:
        """Frames the global bundle adjustment posed again from their own observations."""
        return len(self._reposed)

    def keyframe(self, keyframe_id: int) -> Keyframe:
        return self._keyframes[keyframe_id]

    @property
    def keyframes(self) -> list[Keyframe]:
        return [self._keyframes[k] for k in sorted(self._keyframes)]

    def corrected_keyframe_poses(self) -> dict[int, np.ndarray]:
        """The backend's keyframe estimates as camera-to-world SE(3) (scale taken out of the rotation)."""
        return {k: as_4x4(m) for k, m in self._sim3_estimates().items()}

    def _sim3_estimates(self) -> dict[int, np.ndarray]:
        if self.adjusted is not None:
            return self.adjusted.poses
        start = time.perf_counter()
        estimates = self.backend.estimate() if self._keyframes else {}
        self.counters.seconds["backend"] += time.perf_counter() - start
        return estimates

    def frame_poses(self, corrected: bool) -> list[tuple[int, float, np.ndarray]]:
        """(frame index, timestamp, camera-to-world pose) of every posed frame, in frame order."""
        if self._unsettled:
            raise RuntimeError(f"{len(self._unsettled)} keyframe(s) not settled yet: call finish() first")
        anchors = self._sim3_estimates() if corrected else self._odometry_pose
        reposed = self._reposed if corrected else {}
        poses = []
        for index in sorted(self._frames):
            posed = self._frames[index]
            pose = reposed[index] if index in reposed else posed.pose(anchors)
            poses.append((index, posed.timestamp, pose))
        return poses


def _recent_velocity(track: list[tuple[float, np.ndarray]]) -> tuple[float, np.ndarray] | None:
    """Median speed (units/s) of consecutive (timestamp, position) pairs and the unit direction from
    the first to the last position; None with fewer than two positions or no motion."""
    track = sorted(track, key=lambda item: item[0])
    times = np.array([t for t, _ in track])
    positions = np.array([p for _, p in track])
    if len(track) < 2 or not times[-1] > times[0]:
        return None
    gaps = np.diff(times)
    moving = gaps > 0
    speeds = np.linalg.norm(np.diff(positions, axis=0), axis=1)[moving] / gaps[moving]
    displacement = positions[-1] - positions[0]
    length = float(np.linalg.norm(displacement))
    speed = float(np.median(speeds))
    if not (speed > 0 and length > 0):
        return None
    return speed, displacement / length


def _return_freed_memory() -> None:
    """Hand the C heap's free pages back to the system (glibc's ``malloc_trim``; elsewhere
    nothing). Once large blocks have been freed, glibc serves later ones from its heap and keeps
    their pages when they are freed: at the start of the 9000-frame figure 8's global BA, after the
    loop detector's database was released, the process held 974 MB, of which it gave back 302 MB
    (docs/2026-12-07-global-ba-memory.md)."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


@functools.cache
def _malloc_trim() -> Any:
    try:
        return ctypes.CDLL(None).malloc_trim
    except (AttributeError, OSError):  # not glibc
        return None
