"""One SLAM system you can import: frontend -> object and loop detectors -> verifier -> pose graph.

    from slam_backend import Slam
    slam = Slam(camera)  # mono-vo, symbiolcd2, ssd-mobilenet, pycolmap, gtsam
    slam = Slam(camera, loop_detector=MyDetector(), object_detector="none")
    for frame in frames:  # frontends.types.Frame
        slam.track(frame)
    result = slam.finish()  # trajectories, keyframes, loops, figures
    result.save("out")

Every part is a registered name (with its ``overrides``, as ``--set`` takes them) or an object that
follows the part's Protocol (``frontends.base.Frontend``, ``lcd.base.LoopDetector`` /
``ObjectDetector``, ``slam_backend.verify.Verifier``, ``slam_backend.posegraph.PoseGraphBackend``).
``loop_detector=None`` runs odometry only (the pose graph holds the keyframe chain).

The wiring that makes the system correct lives here and only here: loop corrections move the
frontend's map (``CorrectableFrontend``), loop closing waits for keyframes the frontend may still
refine (``SettlingFrontend``), the frontend masks movable objects the object detector finds
(``MaskingFrontend``), and the next frame's features are extracted while the current one is
tracked (``PrefetchingFrontend``, in ``run``). Checkpoints, fault injection, viewers and output
folders attach from outside (``eval``): they see ``frontend``, ``closing`` and ``state``.
"""

from __future__ import annotations

import csv
import json
import logging
import time
from collections import Counter
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from frontends.base import (
    FRONTENDS,
    CorrectableFrontend,
    Frontend,
    MaskingFrontend,
    SettlingFrontend,
    TrackResult,
    with_lookahead,
)
from frontends.config import load_config
from frontends.safe_io import atomic_path
from frontends.types import CameraIntrinsics, Frame, Keyframe
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS, LoopDetector, ObjectDetector
from slam_backend import plugins
from slam_backend.pipeline import LoopClosing, LoopClosingConfig, LoopRecord
from slam_backend.posegraph import BackendConfig, PoseGraphBackend

log = logging.getLogger(__name__)

TRAJECTORY_FILE = "trajectory_tum.txt"
ODOMETRY_FILE = "trajectory_odometry_tum.txt"
KEYFRAMES_FILE = "keyframes_tum.txt"
LOOPS_FILE = "loops.csv"
FIGURES_FILE = "figures.json"
#: The files ``SlamResult.save`` writes (``symbio run`` writes more: metrics, plots, report).
RESULT_FILES = (TRAJECTORY_FILE, ODOMETRY_FILE, KEYFRAMES_FILE, LOOPS_FILE, FIGURES_FILE)

#: A pose with its frame: (frame index, timestamp in s, 4x4 camera-to-world).
PosedFrame = tuple[int, float, np.ndarray]


@dataclass
class SlamState:
    """What streaming frames through the system produced so far (checkpoints store it)."""

    results: list[TrackResult] = field(default_factory=list)
    #: Position in ``results`` of each frame index (so backfilled results replace earlier ones).
    positions: dict[int, int] = field(default_factory=dict)
    frontend_failures: int = 0
    frontend_seconds: float = 0.0
    total_seconds: float = 0.0
    #: Seconds ``Slam.finish`` took (settling the last keyframes, the global bundle adjustment).
    finish_seconds: float = 0.0
    interrupted: bool = False
    #: Checkpoints written (``--checkpoint-every``), seconds spent writing them, size of the last.
    checkpoints: int = 0
    checkpoint_seconds: float = 0.0
    checkpoint_bytes: int = 0
    #: Checkpoints that could not be written (disk full, ...); the run went on without them.
    checkpoint_failures: int = 0

    @property
    def tracked(self) -> list[TrackResult]:
        return [r for r in self.results if r.pose is not None]

    def add(self, result: TrackResult) -> None:
        """Keep ``result`` without its point observations: loop closing keeps its own compact copy
        for re-posing, and these were ~14 kB per frame for the whole run (130 MB at 9000 frames)."""
        self.positions[result.frame_index] = len(self.results)
        self.results.append(replace(result, observations=None, backfilled=()))
        for late in result.backfilled:
            position = self.positions.get(late.frame_index)
            if position is not None:
                self.results[position] = replace(late, observations=None)


@dataclass
class SlamResult:
    """A finished (or interrupted) run, in memory."""

    #: One result per frame processed (state, odometry pose, keyframe, segment), in stream order;
    #: without ``observations`` (kept only while the run needs them; ``Slam.track`` returns them).
    frames: list[TrackResult]
    #: Loop-corrected poses of the posed frames, in frame order.
    trajectory: list[PosedFrame]
    #: The frontend's own poses of the same frames (no loop correction).
    odometry: list[PosedFrame]
    #: Keyframes in id order, and their corrected camera-to-world poses by keyframe id.
    keyframes: list[Keyframe]
    keyframe_poses: dict[int, np.ndarray]
    #: Every verified loop candidate with the backend's final decision (``accepted``).
    loops: list[LoopRecord]
    #: Counts and timings (frames, keyframes, segments, loops, ms per frame by stage, ...).
    figures: dict[str, Any]

    def save(self, directory: str | Path) -> list[Path]:
        """Write ``RESULT_FILES`` into ``directory`` (created if missing): TUM trajectories, the
        keyframes, ``loops.csv`` and the figures as JSON. Each file is written to a temporary name
        and renamed, so a file there is either complete or the one from before."""
        folder = Path(directory)
        folder.mkdir(parents=True, exist_ok=True)
        paths = [folder / name for name in RESULT_FILES]
        keyframes = [(k.frame_index, k.timestamp, self.keyframe_poses[k.id]) for k in self.keyframes]
        figures = json.dumps(self.figures, indent=1, default=_plain) + "\n"
        writers: list[Callable[[Path], Any]] = [
            lambda path: write_poses(path, self.trajectory),
            lambda path: write_poses(path, self.odometry),
            lambda path: write_poses(path, keyframes),
            lambda path: write_loops_csv(path, self.loops),
            lambda path: path.write_text(figures, encoding="utf-8"),
        ]
        for path, write in zip(paths, writers, strict=True):
            with atomic_path(path) as temporary:
                write(temporary)
        return paths


class Slam:
    """The full system for one camera; see the module docstring."""

    def __init__(
        self,
        camera: CameraIntrinsics,
        *,
        frontend: Frontend | str = "mono-vo",
        loop_detector: LoopDetector | str | None = "symbiolcd2",
        object_detector: ObjectDetector | str | None = "ssd-mobilenet",
        verifier: Any = "pycolmap",
        backend: PoseGraphBackend | str = "gtsam",
        loop_closing: LoopClosingConfig | None = None,
        overrides: Mapping[str, Sequence[str]] | None = None,
    ) -> None:
        """``overrides``: ``key=value`` settings per part named by string, keyed ``frontend``,
        ``detector``, ``object_detector``, ``verifier``, ``backend`` and ``loop_closing`` (the
        latter also applies on top of ``loop_closing``). ``object_detector=None``: no objects."""
        given = dict(overrides or {})
        unknown = set(given) - {
            "frontend",
            "detector",
            "object_detector",
            "verifier",
            "backend",
            "loop_closing",
        }
        if unknown:
            raise ValueError(f"Slam overrides: unknown part(s) {sorted(unknown)}")

        def of(part: str) -> list[str]:
            return list(given.get(part, ()))

        if isinstance(frontend, str):
            frontend = FRONTENDS.load(frontend)(camera, of("frontend"))
        if isinstance(backend, str):
            backend = plugins.BACKENDS.load(backend)(load_config(BackendConfig, None, of("backend")))  # type: ignore[call-arg]
        config = loop_closing or LoopClosingConfig()
        if of("loop_closing"):
            from frontends.config import apply_mapping, parse_override

            for item in of("loop_closing"):
                nested, source = parse_override(item)
                config = apply_mapping(config, nested, source=source)
        if loop_detector is None:
            closing = LoopClosing(backend, config=config)
        else:
            if isinstance(loop_detector, str):
                loop_detector = LOOP_DETECTORS.load(loop_detector)(of("detector"))
            if isinstance(object_detector, str):
                object_detector = OBJECT_DETECTORS.load(object_detector)(of("object_detector"))
            if isinstance(verifier, str):
                verifier = plugins.VERIFIERS.load(verifier)(camera, of("verifier"))
            closing = LoopClosing(backend, loop_detector, object_detector, verifier, config, camera=camera)
        self._attach(frontend, closing, SlamState())

    @classmethod
    def from_parts(cls, frontend: Frontend, closing: LoopClosing, state: SlamState | None = None) -> Slam:
        """A system of a built frontend and loop-closing half, e.g. restored from a checkpoint
        (``state``: its frames so far)."""
        slam = cls.__new__(cls)
        slam._attach(frontend, closing, state or SlamState())
        return slam

    def _attach(self, frontend: Frontend, closing: LoopClosing, state: SlamState) -> None:
        self.frontend = frontend
        self.closing = closing
        self.state = state
        self._finished = False
        if (
            closing.detector is not None
            and closing.config.correct_frontend
            and isinstance(frontend, CorrectableFrontend)
        ):
            closing.on_correction = frontend.apply_correction
        if closing.config.settle_keyframes is None and isinstance(frontend, SettlingFrontend):
            closing.settle_keyframes = frontend.keyframes_in_flux
        if closing.objects is not None and isinstance(frontend, MaskingFrontend):
            frontend.set_dynamic_objects(closing.movable_boxes)

    # -- input -------------------------------------------------------------------------------------

    def track(self, frame: Frame) -> TrackResult:
        """Track one frame and pass the result to loop closing. A frontend that raises loses the
        frame (logged and counted in ``frontend_failures``), it does not end the run."""
        if self._finished:
            raise RuntimeError("Slam.track after finish(): make a new Slam for a new run")
        start = time.perf_counter()
        result = self._track(frame)
        self.state.add(result)
        self.closing.add(result, frame)
        self.state.total_seconds += time.perf_counter() - start
        return result

    def run(
        self, frames: Iterable[Frame], after_frame: Callable[[Frame, TrackResult], None] | None = None
    ) -> SlamResult:
        """Track every frame of ``frames`` (the next frame's features are extracted while one is
        tracked), then ``finish``. ``after_frame`` runs after each frame, outside the timings."""
        for frame in with_lookahead(frames, self.frontend):
            result = self.track(frame)
            if after_frame is not None:
                after_frame(frame, result)
        return self.finish()

    def finish(self) -> SlamResult:
        """End the stream: the last keyframes settle and, if a loop was accepted, the global bundle
        adjustment runs (once; later calls return the same state)."""
        if not self._finished:
            start = time.perf_counter()
            self.closing.finish()
            self.state.finish_seconds = time.perf_counter() - start
            self.state.total_seconds += self.state.finish_seconds
            self._finished = True
        return self.result()

    def result(self) -> SlamResult:
        """The run as it stands (after ``finish``: the final one)."""
        if not self._finished:
            raise RuntimeError("Slam.result before finish(): keyframes may not have settled")
        closing = self.closing
        loops = closing.loops()
        keyframes = closing.keyframes
        return SlamResult(
            frames=list(self.state.results),
            trajectory=closing.frame_poses(corrected=True),
            odometry=closing.frame_poses(corrected=False),
            keyframes=keyframes,
            keyframe_poses=closing.corrected_keyframe_poses(),
            loops=loops,
            figures=slam_figures(self.frontend, closing, self.state, loops),
        )

    def _track(self, frame: Frame) -> TrackResult:
        start = time.perf_counter()
        try:
            result = self.frontend.track(frame)
        except Exception as exc:  # plugin boundary: a failing frame must not end the run
            self.state.frontend_failures += 1
            log.warning(
                "frontend %s failed on %s: %r; frame counted as lost",
                self.frontend.name,
                frame.path or f"frame {frame.index}",
                exc,
                exc_info=log.isEnabledFor(logging.DEBUG),
            )
            result = TrackResult(frame.index, frame.timestamp, "lost", None)
        self.state.frontend_seconds += time.perf_counter() - start
        return result


def slam_figures(
    frontend: Frontend, closing: LoopClosing, state: SlamState, loops: list[LoopRecord]
) -> dict[str, Any]:
    """A run's counts and timings (no ground truth needed)."""
    tracked = state.tracked
    keyframes = closing.keyframes
    segments = {r.segment for r in tracked} | {k.segment for k in keyframes}
    counters = closing.counters
    frames = max(len(state.results), 1)
    return {
        "frontend": frontend.name,
        "loop_closing": closing.detector is not None,
        "detector": closing.detector.name if closing.detector is not None else None,
        "frames": len(state.results),
        "frames_tracked": len(tracked),
        "tracking_lost": sum(r.state == "lost" for r in state.results),
        "frames_initialising": sum(r.state == "initialising" and r.pose is None for r in state.results),
        "frontend_failures": state.frontend_failures,
        "keyframes": len(keyframes),
        "segments": len(segments),
        "fps": len(state.results) / state.total_seconds if state.total_seconds > 0 else None,
        "ms_per_frame_frontend": 1e3 * state.frontend_seconds / frames,
        **{f"ms_per_frame_{k}": 1e3 * v / frames for k, v in sorted(counters.seconds.items())},
        "loops_proposed": len(loops),
        "loops_verified": sum(r.verified for r in loops),
        "loops_accepted": sum(r.accepted for r in loops),
        # Candidates whose map was too thin at first (``LoopClosingConfig.defer_retries``).
        "loops_deferred": sum(r.deferrals > 0 for r in loops),
        "loops_accepted_after_deferral": sum(r.accepted and r.deferrals > 0 for r in loops),
        "loops_accepted_two_view_join": sum(r.accepted and r.two_view for r in loops),
        **global_ba_figures(closing),
        "object_detector_failures": counters.object_detector_failures,
        "loop_detector_failures": counters.loop_detector_failures,
        "verifier_failures": counters.verifier_failures,
        "verifier_timeouts": counters.verifier_timeouts,
    }


def largest_segment(state: SlamState) -> int | None:
    """The map segment with the most posed frames (ties: the lowest id); None if none was posed."""
    per_segment = Counter(r.segment for r in state.tracked)
    return min(per_segment, key=lambda s: (-per_segment[s], s)) if per_segment else None


def global_ba_figures(closing: LoopClosing) -> dict[str, Any]:
    """What the global bundle adjustment did (``global_ba`` false: it did not run)."""
    adjusted = closing.adjusted
    if adjusted is None:
        return {"global_ba": False}
    s = adjusted.stats
    return {
        "global_ba": True,
        "global_ba_keyframes": s.keyframes,
        "global_ba_points": s.points,
        "global_ba_loop_observations": s.loop_observations,
        "global_ba_fused_observations": s.fused_observations,
        "global_ba_median_error_px_before": s.median_error_before_px,
        "global_ba_median_error_px_after": s.median_error_after_px,
        "frames_reposed": closing.frames_reposed,
    }


def write_poses(path: Path, poses: Sequence[PosedFrame]) -> None:
    """A TUM trajectory file (``timestamp tx ty tz qx qy qz qw``, evo)."""
    from evo.core.trajectory import PoseTrajectory3D

    from frontends.trajectory_io import write_trajectory

    if not poses:  # evo cannot build an empty trajectory; an empty file says "no poses" just as well
        path.write_text("", encoding="utf-8")
        return
    trajectory = PoseTrajectory3D(
        poses_se3=[p for _, _, p in poses],
        timestamps=np.array([t for _, t, _ in poses], dtype=np.float64),
    )
    write_trajectory(path, trajectory, "tum")


def write_loops_csv(path: Path, loops: Sequence[LoopRecord], errors: Sequence[Any] | None = None) -> None:
    """One row per verified candidate; with ``errors`` (``eval.lcd_metrics.LoopPoseError`` or None
    per loop) also how far its constraint is from the ground truth."""
    columns = [
        "query", "match", "query_frame", "match_frame", "score", "verified", "inliers", "accepted",
        "scale", "reason", "gt_rotation_error_deg", "gt_direction_error_deg",
    ]  # fmt: skip
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        for r, error in zip(loops, errors or [None] * len(loops), strict=True):
            writer.writerow(
                [
                    r.query, r.match, r.query_frame, r.match_frame, f"{r.score:.6g}", int(r.verified),
                    r.inliers, int(r.accepted), f"{r.scale:.6g}", r.reason,
                    "" if error is None else f"{error.rotation_deg:.3f}",
                    "" if error is None else f"{error.direction_deg:.2f}",
                ]
            )  # fmt: skip


def _plain(value: Any) -> Any:
    """JSON for numpy scalars in the figures."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
