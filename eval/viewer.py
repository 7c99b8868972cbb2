"""The optional rerun viewer of ``symbio run --viewer rerun``: watch a run live, or replay its ``.rrd``.

rerun is an optional extra (``pip install 'symbiolcd2[viewer]'``), imported only when a viewer is
built, so a plain install never needs it. Every ``RerunViewer`` owns its recording stream (no
rerun global state), streams to a running viewer (``connect``, a gRPC URL) or records to a file.

Entity paths (timelines: ``frame`` = frame index, ``time`` = frame timestamp in seconds, logged
as a duration so that epoch and relative timestamps both read as plain seconds):

* ``world``: view coordinates RDF (the frontend's map frame is its first camera's frame);
* ``world/camera``: the current camera-to-world pose (Transform3D), ``world/camera/image`` its
  Pinhole when the intrinsics are given;
* ``world/trajectory/odometry``: the frontend's camera centres so far, one strip per map segment
  (re-logged every ``trajectory_every`` frames: logging the growing strip each frame would make
  the recording quadratic in the run length);
* ``world/keyframes``: keyframe camera centres;
* ``world/loops/accepted`` (green), ``world/loops/rejected`` (red): a line between the two
  keyframe centres of each verified candidate, with the latest decision for each pair;
* ``world/trajectory/final`` (loop-closed) and ``world/trajectory/final_odometry``: the backend's
  two trajectories at the end of the run (static, so they show at every time);
* ``keyframe/image`` (downscaled by ``IMAGE_SCALE``), ``keyframe/keypoints``, ``keyframe/objects``
  (boxes labelled "class score"), and ``keyframe/graph/tier1`` .. ``tier3``: the SymbioLCD2 graph's
  edges in the image (tier 1 object-object, 2 object-feature inside the box, 3 object-feature
  within the margin around it). The scene node and its tier-0 edges have no place in the image
  and are not drawn.

``LabelledGraph`` stores no node positions, so the viewer lays the nodes out again from the keyframe
in ``lcd.graph.build_graph``'s node order (scene, objects, distance nodes, per object its inside
then around features, background features), trying the keyframe's objects as the detector's
default filter keeps them, all of them, and none. It draws the graph's own edges when that layout
reproduces the graph's node kinds and object labels exactly; otherwise (a graph built with another
filter or margin) it draws the three tiers computed from the keyframe geometry directly (filtered
objects, ``margin_px``), so the picture is never silently wrong about which graph it shows.
"""

from __future__ import annotations

import logging
import types
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from frontends.base import TrackResult
from frontends.errors import ConfigError
from frontends.types import CameraIntrinsics, DetectedObject, Frame, Keyframe
from lcd.graph import AROUND, BACKGROUND, DISTANCE, INSIDE, OBJECT, SCENE, LabelledGraph, node_label
from lcd.objects.filtering import filter_objects
from slam_backend.pipeline import LoopRecord

log = logging.getLogger(__name__)

MISSING_EXTRA = "--viewer rerun needs the optional extra: pip install 'symbiolcd2[viewer]'"
#: Keyframe images (and their keypoints, boxes and graph) are shown at this scale to keep the
#: recording small.
IMAGE_SCALE = 0.5
#: The paper's tier-3 margin (``lcd.graph.GraphConfig.margin_px``).
MARGIN_PX = 25.0
#: Longest wait for the recording to reach its file or viewer in ``close``.
FLUSH_SECONDS = 30.0

ACCEPTED = (40, 200, 60)
REJECTED = (220, 40, 40)
ODOMETRY = (150, 150, 150)
FINAL = (30, 120, 255)
KEYPOINTS = (255, 200, 0)
TIER_COLOURS = {1: (255, 255, 0), 2: (0, 255, 120), 3: (0, 200, 255)}
#: Which tier an edge belongs to, by the kind of its non-object end.
_TIER_OF_KIND = {DISTANCE: 1, INSIDE: 2, AROUND: 3}


class RerunViewer:
    """Logs frames, keyframes, loops and trajectories of one run to rerun."""

    def __init__(
        self,
        rrd_path: Path | None,
        connect: str | None = None,
        *,
        camera: CameraIntrinsics | None = None,
        trajectory_every: int = 10,
    ) -> None:
        """Record to ``rrd_path``, or stream to the viewer at gRPC URL ``connect`` when given."""
        try:
            import rerun as rr
        except ImportError:
            raise ConfigError(MISSING_EXTRA) from None
        if not hasattr(rr.RecordingStream, "set_time") or not hasattr(rr.RecordingStream, "connect_grpc"):
            raise ConfigError(
                f"--viewer rerun needs rerun-sdk >= 0.23 (set_time, connect_grpc), found "
                f"{getattr(rr, '__version__', 'unknown')}: pip install -U 'symbiolcd2[viewer]'"
            )
        if connect is None and rrd_path is None:
            raise ConfigError("--viewer rerun needs a .rrd path to record to, or a viewer URL to connect to")
        if trajectory_every < 1:
            raise ConfigError(f"viewer: trajectory_every must be >= 1, got {trajectory_every}")
        self._rr: types.ModuleType = rr
        self.rec = rr.RecordingStream("symbiolcd2")
        # Wall-clock timelines would make two recordings of the same run differ.
        self.rec.set_log_time_enabled(False)
        self.rec.set_log_tick_enabled(False)
        if connect is not None:
            self.rec.connect_grpc(connect)
        else:
            assert rrd_path is not None
            rrd_path.parent.mkdir(parents=True, exist_ok=True)
            self.rec.save(rrd_path)
        self.connect = connect
        self.trajectory_every = trajectory_every
        #: segment -> frame index -> camera centre, for the live odometry strips.
        self._centres: dict[int, dict[int, np.ndarray]] = {}
        self._unlogged_frames = 0
        self._keyframe_centres: list[np.ndarray] = []
        #: (query, match) -> (accepted, query centre, match centre, label): latest decision per pair.
        self._loops: dict[tuple[int, int], tuple[bool, np.ndarray, np.ndarray, str]] = {}
        self._closed = False
        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        if camera is not None:
            self.rec.log(
                "world/camera/image",
                rr.Pinhole(
                    image_from_camera=camera.K,
                    resolution=[camera.width, camera.height],
                    image_plane_distance=0.2,
                ),
                static=True,
            )

    def _set_time(self, index: int, timestamp: float) -> None:
        self.rec.set_time("frame", sequence=int(index))
        self.rec.set_time("time", duration=float(timestamp))

    def frame(self, frame: Frame, result: TrackResult) -> None:
        """The camera pose of one frame, and its centre on the growing odometry strip."""
        rr = self._rr
        self._set_time(frame.index, frame.timestamp)
        for earlier in result.backfilled:  # frames posed after the fact (monocular initialisation)
            if earlier.pose is not None:
                self._centres.setdefault(earlier.segment, {})[earlier.frame_index] = _centre(earlier.pose)
        if result.pose is not None:
            pose = np.asarray(result.pose, dtype=np.float64)
            self.rec.log("world/camera", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
            self._centres.setdefault(result.segment, {})[result.frame_index] = _centre(pose)
        self._unlogged_frames += 1
        if self._unlogged_frames >= self.trajectory_every:
            self._log_odometry()

    def _log_odometry(self) -> None:
        strips = [
            np.array([points[k] for k in sorted(points)], dtype=np.float32)
            for _, points in sorted(self._centres.items())
            if len(points) >= 2
        ]
        self.rec.log("world/trajectory/odometry", self._rr.LineStrips3D(strips, colors=ODOMETRY))
        self._unlogged_frames = 0

    def keyframe(self, keyframe: Keyframe, graph: LabelledGraph | None = None) -> None:
        """A keyframe's image, keypoints, objects and (with ``graph``) its graph edges."""
        rr = self._rr
        self._set_time(keyframe.frame_index, keyframe.timestamp)
        self._keyframe_centres.append(_centre(keyframe.pose))
        self.rec.log(
            "world/keyframes",
            rr.Points3D(np.array(self._keyframe_centres, dtype=np.float32), colors=FINAL, radii=-2.0),
        )
        if keyframe.image is not None:
            self.rec.log("keyframe/image", rr.Image(_display_image(keyframe.image)))
        else:  # not the previous keyframe's image under this one's keypoints
            self.rec.log("keyframe/image", rr.Clear(recursive=False))
        keypoints = np.asarray(keyframe.keypoints, dtype=np.float64).reshape(-1, 2)
        self.rec.log(
            "keyframe/keypoints",
            rr.Points2D(_to_display(keypoints), colors=KEYPOINTS, radii=-1.5),
        )
        boxes = np.array([o.box for o in keyframe.objects], dtype=np.float64).reshape(-1, 4)
        self.rec.log(
            "keyframe/objects",
            rr.Boxes2D(
                array=boxes * IMAGE_SCALE,
                array_format=rr.Box2DFormat.XYXY,
                labels=[f"{o.label} {o.score:.2f}" for o in keyframe.objects],
            ),
        )
        tiers = graph_segments(keyframe, graph) if graph is not None else {}
        for tier in (1, 2, 3):
            segments = tiers.get(tier, np.zeros((0, 2, 2)))
            self.rec.log(
                f"keyframe/graph/tier{tier}",
                rr.LineStrips2D([_to_display(s) for s in segments], colors=TIER_COLOURS[tier], radii=-1.0),
            )

    def loop(self, record: LoopRecord, query_pose: np.ndarray, match_pose: np.ndarray) -> None:
        """A verified candidate as a line between its keyframes' camera centres (latest decision)."""
        label = f"{record.query}->{record.match} inliers={record.inliers} {record.reason}".strip()
        self._loops[(record.query, record.match)] = (
            record.accepted,
            _centre(query_pose),
            _centre(match_pose),
            label,
        )
        for accepted, path, colour in ((True, "accepted", ACCEPTED), (False, "rejected", REJECTED)):
            chosen = [v for _, v in sorted(self._loops.items()) if v[0] == accepted]
            self.rec.log(
                f"world/loops/{path}",
                self._rr.LineStrips3D(
                    [np.array([q, m], dtype=np.float32) for _, q, m, _ in chosen],
                    colors=colour,
                    labels=[text for _, _, _, text in chosen],
                ),
            )

    def trajectories(
        self,
        final: Sequence[tuple[int, float, np.ndarray]],
        odometry: Sequence[tuple[int, float, np.ndarray]],
    ) -> None:
        """The backend's loop-closed and odometry trajectories, once at the end (static)."""
        for path, poses, colour in (("final", final, FINAL), ("final_odometry", odometry, ODOMETRY)):
            points = np.array([_centre(p) for _, _, p in poses], dtype=np.float32).reshape(-1, 3)
            self.rec.log(
                f"world/trajectory/{path}",
                self._rr.LineStrips3D([points] if len(points) >= 2 else [], colors=colour),
                static=True,
            )

    def close(self) -> None:
        """Log what is pending and finish the recording, so the ``.rrd`` is complete and readable."""
        if self._closed:
            return
        self._closed = True
        if self._unlogged_frames:
            self._log_odometry()
        try:
            self.rec.flush(timeout_sec=FLUSH_SECONDS)
        except RuntimeError as error:
            if self.connect is None:
                raise
            # A viewer that went away must not cost the run its other outputs.
            log.warning("rerun viewer at %s did not receive the recording: %s", self.connect, error)
        finally:
            self.rec.disconnect()

    def __enter__(self) -> RerunViewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _centre(pose: np.ndarray) -> np.ndarray:
    return np.asarray(pose, dtype=np.float64)[:3, 3].copy()


def _display_image(image: np.ndarray) -> np.ndarray:
    """The image downscaled by ``IMAGE_SCALE``, grey or RGB (OpenCV images are BGR)."""
    height, width = image.shape[:2]
    size = (max(1, round(width * IMAGE_SCALE)), max(1, round(height * IMAGE_SCALE)))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    if small.ndim == 3 and small.shape[2] == 3:
        return cv2.cvtColor(small, cv2.COLOR_BGR2RGB)
    if small.ndim == 3 and small.shape[2] == 4:
        return cv2.cvtColor(small, cv2.COLOR_BGRA2RGBA)
    return small


def _to_display(pixels: np.ndarray) -> np.ndarray:
    """OpenCV pixel coordinates (centres at integers) to rerun's (centres at +0.5), scaled."""
    return ((np.asarray(pixels, dtype=np.float64) + 0.5) * IMAGE_SCALE).astype(np.float32)


def _image_size(keyframe: Keyframe) -> tuple[int, int]:
    """(width, height) as ``SymbioLCD2.graph_of`` takes it for the object filter."""
    if keyframe.image is not None:
        return keyframe.image.shape[1], keyframe.image.shape[0]
    extent = keyframe.keypoints.max(axis=0) + 1 if len(keyframe.keypoints) else np.ones(2)
    return int(extent[0]), int(extent[1])


def _centres_of(objects: Sequence[DetectedObject]) -> np.ndarray:
    boxes = np.array([o.box for o in objects], dtype=np.float64).reshape(-1, 4)
    return np.column_stack([(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2])


def _layout(
    keypoints: np.ndarray, objects: Sequence[DetectedObject], tiers: int, background: bool, margin_px: float
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Node positions (NaN for the scene node), kinds and labels of the object nodes, in
    ``build_graph``'s node order; feature nodes sit on their keypoint, distance nodes between
    their two objects."""
    positions: list[np.ndarray] = [np.full((1, 2), np.nan)]
    kinds: list[np.ndarray] = [np.array([SCENE])]
    object_labels: list[int] = []

    def add(points: np.ndarray, kind: int) -> None:
        positions.append(points.reshape(-1, 2))
        kinds.append(np.full(len(points), kind))

    attached = np.zeros(len(keypoints), dtype=bool)
    if tiers >= 2 and objects:
        centres = _centres_of(objects)
        add(centres, OBJECT)
        object_labels = [node_label(OBJECT, o.label) for o in objects]
        if len(objects) >= 2:
            first, second = np.triu_indices(len(objects), k=1)
            add((centres[first] + centres[second]) / 2, DISTANCE)
        x, y = keypoints[:, 0], keypoints[:, 1]
        for obj in objects:
            x0, y0, x1, y1 = obj.box
            inside = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
            members = [(inside, INSIDE)]
            if tiers >= 3:
                m = margin_px
                near = (x >= x0 - m) & (x < x1 + m) & (y >= y0 - m) & (y < y1 + m) & ~inside
                members.append((near, AROUND))
            for mask, kind in members:
                if mask.any():
                    add(keypoints[mask], kind)
                    attached |= mask
    if background or tiers < 2:
        add(keypoints[~attached], BACKGROUND)
    return np.concatenate(positions), np.concatenate(kinds), object_labels


def _tier_segments(positions: np.ndarray, kinds: np.ndarray, edges: np.ndarray) -> dict[int, np.ndarray]:
    """Edges as (E, 2, 2) pixel segments per tier; edges at the scene node are left out."""
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    ends = kinds[edges]
    segments: dict[int, np.ndarray] = {}
    for kind, tier in _TIER_OF_KIND.items():
        chosen = edges[((ends == kind).any(axis=1)) & ~((ends == SCENE).any(axis=1))]
        segments[tier] = positions[chosen].reshape(-1, 2, 2)
    return segments


def graph_segments(
    keyframe: Keyframe, graph: LabelledGraph, margin_px: float = MARGIN_PX
) -> dict[int, np.ndarray]:
    """Tier (1, 2, 3) -> (E, 2, 2) segments in full-resolution pixels of ``graph``'s edges."""
    keypoints = np.asarray(keyframe.keypoints, dtype=np.float64).reshape(-1, 2)
    background = bool((graph.kinds == BACKGROUND).any())
    graph_object_labels = graph.labels[graph.kinds == OBJECT].tolist()
    filtered = filter_objects(keyframe.objects, _image_size(keyframe))
    for objects in (filtered, list(keyframe.objects), []):
        for tiers in (3, 2):
            positions, kinds, labels = _layout(keypoints, objects, tiers, background, margin_px)
            if (
                len(kinds) == graph.num_nodes
                and np.array_equal(kinds, graph.kinds)
                and labels == graph_object_labels
            ):
                return _tier_segments(positions, kinds, graph.edges)
    return geometric_segments(keypoints, filtered, margin_px)


def geometric_segments(
    keypoints: np.ndarray, objects: Sequence[DetectedObject], margin_px: float = MARGIN_PX
) -> dict[int, np.ndarray]:
    """The three tiers straight from the geometry: object centres to each other (1), to the
    keypoints inside their box (2) and within ``margin_px`` outside it (3)."""
    keypoints = np.asarray(keypoints, dtype=np.float64).reshape(-1, 2)
    centres = _centres_of(objects)
    segments: dict[int, list[np.ndarray]] = {1: [], 2: [], 3: []}
    if len(objects) >= 2:
        first, second = np.triu_indices(len(objects), k=1)
        segments[1].append(np.stack([centres[first], centres[second]], axis=1))
    x, y = keypoints[:, 0], keypoints[:, 1]
    for obj, centre in zip(objects, centres, strict=True):
        x0, y0, x1, y1 = obj.box
        m = margin_px
        inside = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
        near = (x >= x0 - m) & (x < x1 + m) & (y >= y0 - m) & (y < y1 + m) & ~inside
        for tier, mask in ((2, inside), (3, near)):
            points = keypoints[mask]
            segments[tier].append(np.stack([np.broadcast_to(centre, points.shape), points], axis=1))
    return {
        tier: np.concatenate(parts).reshape(-1, 2, 2) if parts else np.zeros((0, 2, 2))
        for tier, parts in segments.items()
    }
