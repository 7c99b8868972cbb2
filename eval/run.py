"""The ``symbio run`` pipeline as a library: stream a dataset through a frontend and loop closing,
measure it and write its output folder (the command line is ``eval.run_cli``; its ``--help`` says
what every output file holds).

frontend (each frame) -> object detector, loop detector (each keyframe) -> verifier -> backend
(``slam_backend.pipeline.LoopClosing``). ``run_odometry`` writes, into a claimed output folder
(``eval.outputs.RunFolder``), the loop-closed and odometry trajectories, the keyframes, ``loops.csv``,
the plots, ``report.html`` and last ``metrics.json`` (``complete`` true once everything else is in
place).
"""

from __future__ import annotations

import contextlib
import csv
import itertools
import logging
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from evo.core import metrics
from evo.core.geometry import GeometryException
from evo.core.trajectory import PosePath3D, PoseTrajectory3D
from tqdm import tqdm

from eval import checkpoint
from eval.checkpoint import Checkpointer, RunState
from eval.components import Components
from eval.inject import InjectedDataset
from eval.lcd_eval import default_object_detector
from eval.lcd_metrics import LoopPoseError, gt_references, has_reachable_loop, is_true_match, loop_pose_error
from eval.outputs import RunFolder
from eval.report import (
    APE_FILE,
    REPORT_FILE,
    TOP_VIEW_FILE,
    aligned,
    with_ground_truth,
    write_plots,
    write_report,
)
from eval.viewer import RerunViewer
from frontends.base import (
    CorrectableFrontend,
    Frontend,
    MaskingFrontend,
    SettlingFrontend,
    TrackResult,
    with_lookahead,
)
from frontends.cli_common import flat_json
from frontends.config import load_config
from frontends.datasets import Dataset
from frontends.datasets.base import SKIP_CAUSES
from frontends.errors import display_path
from frontends.trajectory_io import write_trajectory
from frontends.types import Frame
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS
from slam_backend.pipeline import LoopClosing, LoopClosingConfig, LoopRecord
from slam_backend.posegraph import BACKENDS, BackendConfig
from slam_backend.verify import VERIFIERS

log = logging.getLogger(__name__)

TRAJECTORY_FILE = "trajectory_tum.txt"
ODOMETRY_FILE = "trajectory_odometry_tum.txt"
KEYFRAMES_FILE = "keyframes_tum.txt"
LOOPS_FILE = "loops.csv"
METRICS_FILE = "metrics.json"
RRD_FILE = "run.rrd"
OUTPUT_FILES = (TRAJECTORY_FILE, ODOMETRY_FILE, KEYFRAMES_FILE, LOOPS_FILE, METRICS_FILE, REPORT_FILE)
#: RPE is measured over this much time (s), a few keyframes at walking speed.
RPE_DELTA_S = 1.0


@dataclass
class PipelineRun:
    """What streaming frames through the pipeline produced so far."""

    results: list[TrackResult] = field(default_factory=list)
    #: Position in ``results`` of each frame index (so backfilled results replace earlier ones).
    positions: dict[int, int] = field(default_factory=dict)
    frontend_failures: int = 0
    frontend_seconds: float = 0.0
    total_seconds: float = 0.0
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
        self.positions[result.frame_index] = len(self.results)
        self.results.append(result)
        for late in result.backfilled:
            position = self.positions.get(late.frame_index)
            if position is not None:
                self.results[position] = late


def track_frame(frontend: Frontend, frame: Frame, run: PipelineRun) -> TrackResult:
    """The frontend's result for ``frame``; if it raises, the frame is lost (logged, counted)."""
    start = time.perf_counter()
    try:
        result = frontend.track(frame)
    except Exception as exc:  # plugin boundary: a failing frame must not end the run
        run.frontend_failures += 1
        log.warning(
            "frontend %s failed on %s: %r; frame counted as lost",
            frontend.name,
            frame.path or f"frame {frame.index}",
            exc,
            exc_info=log.isEnabledFor(logging.DEBUG),
        )
        result = TrackResult(frame.index, frame.timestamp, "lost", None)
    run.frontend_seconds += time.perf_counter() - start
    return result


def stream_frames(
    frames: Iterable[Frame],
    frontend: Frontend,
    loop_closing: LoopClosing,
    run: PipelineRun,
    viewer: RerunViewer | None = None,
    after_frame: Callable[[Frame], None] | None = None,
) -> None:
    """Each frame through the frontend and loop closing; ``after_frame`` (e.g. a checkpoint) runs
    once the frame is done, outside the timings."""
    for frame in with_lookahead(frames, frontend):
        start = time.perf_counter()
        result = track_frame(frontend, frame, run)
        run.add(result)
        loop_closing.add(result, frame)
        run.total_seconds += time.perf_counter() - start
        if viewer is not None:
            viewer.frame(frame, result)
        if after_frame is not None:
            after_frame(frame)
    start = time.perf_counter()
    loop_closing.finish()  # the last keyframes settle when the stream ends
    run.total_seconds += time.perf_counter() - start


def attach_viewer(viewer: RerunViewer, closing: LoopClosing) -> None:
    """Keyframes (with objects and the detector's graph) and loops go to the viewer as they happen."""
    closing.on_keyframe = viewer.keyframe
    closing.on_loop = lambda record: viewer.loop(
        record, closing.keyframe(record.query).pose, closing.keyframe(record.match).pose
    )


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


def build_loop_closing(dataset: Dataset, components: Components | None) -> LoopClosing:
    """The loop-closing half for ``components``; None or ``--no-loops``: the backend chain only."""
    c = components or Components()
    backend = BACKENDS.load(c.backend)(load_config(BackendConfig, None, c.of("backend")))  # type: ignore[call-arg]
    config = load_config(LoopClosingConfig, None, c.of("loop_closing"))
    if components is None:
        return LoopClosing(backend, config=config)
    object_name = c.object_detector or default_object_detector(dataset)
    return LoopClosing(
        backend,
        LOOP_DETECTORS.load(c.detector)(c.of("detector")),
        OBJECT_DETECTORS.load(object_name)(c.of("object_detector")),
        VERIFIERS.load(c.verifier)(dataset.camera, c.of("verifier")),
        config,
        camera=dataset.camera,
    )


def run_odometry(
    dataset: Dataset,
    frontend: Frontend,
    out: Path | RunFolder,
    *,
    loop_closing: LoopClosing | None = None,
    max_frames: int | None = None,
    progress: bool = True,
    tolerance: int = 0,
    config: dict[str, Any] | None = None,
    viewer: RerunViewer | None = None,
    checkpointer: Checkpointer | None = None,
    resume: RunState | None = None,
) -> dict[str, Any]:
    """Stream ``dataset`` through ``frontend`` (and ``loop_closing``, default: odometry only), write
    the trajectories, loops and metrics to ``out``; returns the figures of ``metrics.json``.

    ``out``: a claimed ``RunFolder``, or a folder path that is claimed for the call (refused when it
    holds files symbio did not write, or another command is writing there: see ``eval.outputs``).

    ``checkpointer`` saves the state every N frames (deleted once the outputs are written);
    ``resume``: the state of a checkpoint (its ``frontend`` and ``closing`` must be the ones passed),
    whose processed frames are skipped. If anything stops the run early (including
    KeyboardInterrupt), what was processed is written first and the exception re-raised.
    """
    with contextlib.ExitStack() as stack:
        folder = out if isinstance(out, RunFolder) else stack.enter_context(run_folder(out))
        return _run_into(
            folder, dataset, frontend, loop_closing, max_frames, progress, tolerance, config, viewer,
            checkpointer, resume,
        )  # fmt: skip


def run_folder(
    path: Path,
    *,
    overwrite: bool = False,
    resume: bool = False,
    command: str = "symbio run",
    extra_names: tuple[str, ...] = (),
) -> RunFolder:
    """The output folder of ``symbio run`` at ``path`` (unclaimed; use it as a context manager);
    ``command`` and ``extra_names``: those of a command that writes more (``symbio demo``)."""
    return RunFolder(
        path,
        command,
        names=(*OUTPUT_FILES, TOP_VIEW_FILE, APE_FILE, RRD_FILE, checkpoint.HEADER_FILE, *extra_names),
        keep=(checkpoint.HEADER_FILE, "checkpoint-*.pkl"),
        overwrite=overwrite,
        resume=resume,
    )


def _run_into(
    folder: RunFolder,
    dataset: Dataset,
    frontend: Frontend,
    loop_closing: LoopClosing | None,
    max_frames: int | None,
    progress: bool,
    tolerance: int,
    config: dict[str, Any] | None,
    viewer: RerunViewer | None,
    checkpointer: Checkpointer | None,
    resume: RunState | None,
) -> dict[str, Any]:
    closing = loop_closing if loop_closing is not None else build_loop_closing(dataset, None)
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
    if viewer is not None:
        attach_viewer(viewer, closing)
    run = PipelineRun() if resume is None else resume.run
    total = len(dataset) if max_frames is None else min(max_frames, len(dataset))
    stream: Iterable[Frame] = (
        itertools.islice(dataset, max_frames)
        if resume is None
        else checkpoint.remaining(dataset, max_frames, resume)
    )
    if checkpointer is not None:
        stream = checkpointer.track(stream)
    after_frame = (
        (lambda frame: checkpointer.after_frame(frame, frontend, closing, run)) if checkpointer else None
    )
    try:
        with tqdm(
            stream,
            total=total,
            initial=len(run.results),
            disable=not progress,
            unit="frame",
            desc=f"run {frontend.name}",
        ) as frames:
            stream_frames(frames, frontend, closing, run, viewer, after_frame)
    except BaseException:
        run.interrupted = True
        log.warning("run stopped after %d frames; writing what exists to %s", len(run.results), folder.root)
        closing.finish()
        write_outputs(folder, dataset, frontend, closing, run, tolerance, config or {}, viewer)
        raise
    figures = write_outputs(folder, dataset, frontend, closing, run, tolerance, config or {}, viewer)
    if run.results and all(r.pose is None for r in run.results):
        log.warning(
            "%s posed none of the %d frames: it never initialised. Likely causes: too little parallax "
            "(a camera that stands still or only rotates), too much motion between frames (a low frame "
            "rate or skipped frames), too few features (dark, blurred or textureless images), or wrong "
            "intrinsics",
            frontend.name, len(run.results),
        )  # fmt: skip
    if checkpointer is not None:
        checkpoint.discard(folder.root)
    return figures


def write_outputs(
    folder: RunFolder,
    dataset: Dataset,
    frontend: Frontend,
    closing: LoopClosing,
    run: PipelineRun,
    tolerance: int,
    config: dict[str, Any],
    viewer: RerunViewer | None = None,
) -> dict[str, Any]:
    final = closing.frame_poses(corrected=True)
    odometry = closing.frame_poses(corrected=False)
    if viewer is not None:
        viewer.trajectories(final, odometry)
        viewer.close()
    with folder.atomic(TRAJECTORY_FILE) as path:
        write_poses(path, [p for _, _, p in final], [t for _, t, _ in final])
    with folder.atomic(ODOMETRY_FILE) as path:
        write_poses(path, [p for _, _, p in odometry], [t for _, t, _ in odometry])
    keyframes = closing.keyframes
    corrected = closing.corrected_keyframe_poses()
    with folder.atomic(KEYFRAMES_FILE) as path:
        write_poses(path, [corrected[k.id] for k in keyframes], [k.timestamp for k in keyframes])
    loops = closing.loops()
    with folder.atomic(LOOPS_FILE) as path:
        write_loops_csv(path, loops, loop_pose_errors(dataset, loops))
    figures = run_figures(dataset, frontend, closing, run, final, odometry, loops, tolerance)
    images = write_plots(folder, dataset, odometry, final, loops, {k.id: k.frame_index for k in keyframes})
    write_report(folder, figures, config, images, loops)
    # Last: a metrics.json that says "complete" means every other output above is in place.
    folder.write_text(METRICS_FILE, flat_json(figures))
    return figures


def write_poses(path: Path, poses: list[np.ndarray], timestamps: list[float]) -> None:
    if not poses:  # evo cannot build an empty trajectory; an empty file says "no poses" just as well
        path.write_text("", encoding="utf-8")
        return
    trajectory = PoseTrajectory3D(poses_se3=poses, timestamps=np.asarray(timestamps, dtype=np.float64))
    write_trajectory(path, trajectory, "tum")


def write_loops_csv(
    path: Path, loops: list[LoopRecord], errors: list[LoopPoseError | None] | None = None
) -> None:
    """One row per verified candidate; with GT poses also how far its constraint is from the GT."""
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


def loop_pose_errors(dataset: Dataset, loops: list[LoopRecord]) -> list[LoopPoseError | None]:
    """Per loop, its constraint's error against the GT poses of its two frames (None without them)."""
    gt = dataset.gt_poses
    errors: list[LoopPoseError | None] = []
    for r in loops:
        if gt is None or r.relative is None:
            errors.append(None)
            continue
        match, query = gt[r.match_frame], gt[r.query_frame]
        known = np.isfinite(match).all() and np.isfinite(query).all()
        errors.append(loop_pose_error(match, query, r.relative) if known else None)
    return errors


def run_figures(
    dataset: Dataset,
    frontend: Frontend,
    closing: LoopClosing,
    run: PipelineRun,
    final: list[tuple[int, float, np.ndarray]],
    odometry: list[tuple[int, float, np.ndarray]],
    loops: list[LoopRecord],
    tolerance: int,
) -> dict[str, Any]:
    tracked = run.tracked
    keyframes = closing.keyframes
    segments = {r.segment for r in tracked} | {k.segment for k in keyframes}
    per_segment = Counter(r.segment for r in tracked)
    segment = min(per_segment, key=lambda s: (-per_segment[s], s)) if per_segment else None
    in_segment = {r.frame_index for r in tracked if r.segment == segment}
    before = trajectory_errors(dataset, [p for p in odometry if p[0] in in_segment])
    after = trajectory_errors(dataset, [p for p in final if p[0] in in_segment])
    after_all = trajectory_errors(dataset, final)
    counters = closing.counters
    frames = max(len(run.results), 1)
    figures: dict[str, Any] = {
        "dataset": display_path(dataset.root),
        "format": dataset.format_name,
        "frontend": frontend.name,
        "loop_closing": closing.detector is not None,
        "detector": closing.detector.name if closing.detector is not None else None,
        "frames": len(run.results),
        "frames_tracked": len(tracked),
        "tracking_lost": sum(r.state == "lost" for r in run.results),
        "frames_initialising": sum(r.state == "initialising" and r.pose is None for r in run.results),
        "frontend_failures": run.frontend_failures,
        "frames_skipped": len(dataset.skipped),
        **{
            f"frames_skipped_{cause.replace(' ', '_')}": sum(s.cause == cause for s in dataset.skipped)
            for cause in SKIP_CAUSES
        },
        "keyframes": len(keyframes),
        "segments": len(segments),
        "fps": len(run.results) / run.total_seconds if run.total_seconds > 0 else None,
        "ms_per_frame_frontend": 1e3 * run.frontend_seconds / frames,
        **{f"ms_per_frame_{k}": 1e3 * v / frames for k, v in sorted(counters.seconds.items())},
        "ate_rmse_before": before[0],
        "ate_rmse_after": after[0],
        "ate_rmse_after_all": after_all[0],
        "rpe_rmse_before": before[1],
        "rpe_rmse_after": after[1],
        "ate_segment": segment if before[0] is not None else None,
        "ate_frames": before[2],
        "path_length": gt_path_length(dataset, run.results),
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
        **(dataset.injection.figures() if isinstance(dataset, InjectedDataset) else {}),
        "interrupted": run.interrupted,
        # metrics.json is written after every other output: true means all of them are in place.
        "complete": not run.interrupted,
        "checkpoints": run.checkpoints,
        "ms_per_checkpoint": 1e3 * run.checkpoint_seconds / run.checkpoints if run.checkpoints else None,
        "checkpoint_bytes": run.checkpoint_bytes if run.checkpoints else None,
        "checkpoint_failures": run.checkpoint_failures,
    }
    figures.update(loop_truth(dataset, loops, keyframes, tolerance))
    return figures


def loop_truth(
    dataset: Dataset, loops: list[LoopRecord], keyframes: list[Any], tolerance: int
) -> dict[str, Any]:
    """False accepted loops, and precision/recall of the accepted loops against the GT loop pairs.

    A loop is false when its constraint contradicts the GT poses (``LoopPoseError.wrong``); without
    GT poses for its frames, when it lies outside the GT loop pairs' band (``tolerance`` frames).
    The band is a place labeller's (synthetic scenes: covisible views within 1 m): views of the
    same wall farther apart fall outside it and still give right constraints (measured with the
    earlier 0.6 m band: within 0.4 deg and 1 deg of the GT), so ``loops_outside_gt_band`` counts
    those separately. Recall
    counts the query keyframes that had a GT loop to an earlier keyframe (within ``tolerance``
    frames) and got an accepted loop inside the band."""
    accepted = [r for r in loops if r.accepted]
    errors = loop_pose_errors(dataset, accepted)
    pairs, _ = dataset.loop_pairs()
    figures: dict[str, Any] = {
        "false_loops_accepted": None,
        "loops_outside_gt_band": None,
        "lcd_precision": None,
        "lcd_recall": None,
        "gt_loop_queries": None,
    }
    in_band: list[bool | None] = [None] * len(accepted)
    if pairs is not None:
        references = gt_references(pairs)
        in_band = [is_true_match(r.match_frame, references.get(r.query_frame), tolerance) for r in accepted]
        true = [r for r, inside in zip(accepted, in_band, strict=True) if inside]
        frames = [k.frame_index for k in keyframes]
        reachable = {
            f for i, f in enumerate(frames) if has_reachable_loop(references.get(f), frames[:i], tolerance)
        }
        found = {r.query_frame for r in true} & reachable
        figures.update(
            loops_outside_gt_band=len(accepted) - len(true),
            lcd_precision=len(true) / len(accepted) if accepted else None,
            lcd_recall=len(found) / len(reachable) if reachable else None,
            gt_loop_queries=len(reachable),
        )
    verdicts = [
        error.wrong if error is not None else (None if inside is None else not inside)
        for error, inside in zip(errors, in_band, strict=True)
    ]
    if pairs is not None or dataset.gt_poses is not None:
        figures["false_loops_accepted"] = sum(bool(v) for v in verdicts)
    return figures


def trajectory_errors(
    dataset: Dataset, poses: list[tuple[int, float, np.ndarray]]
) -> tuple[float | None, float | None, int]:
    """(APE translation RMSE, RPE translation RMSE over ``RPE_DELTA_S``, frames) after Sim(3)
    Umeyama alignment to the GT (evo); None without GT or with fewer than 3 posed GT frames."""
    kept, reference = with_ground_truth(dataset, poses)
    if reference is None:
        return None, None, len(kept)
    try:
        estimate = aligned(kept, reference)
    except GeometryException as exc:  # e.g. a frontend that never moved: Umeyama is degenerate
        log.warning("Sim(3) alignment to the ground truth failed (%s); no ATE", exc)
        return None, None, len(kept)
    stamps = reference.timestamps
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((reference, estimate))
    ate = float(ape.get_statistic(metrics.StatisticsType.rmse))
    rpe_value = None
    rate = (len(stamps) - 1) / max(float(stamps[-1] - stamps[0]), 1e-9)
    delta = max(1, round(RPE_DELTA_S * rate))
    if len(kept) > delta:
        rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta, metrics.Unit.frames, all_pairs=False)
        rpe.process_data((reference, estimate))
        rpe_value = float(rpe.get_statistic(metrics.StatisticsType.rmse))
    return ate, rpe_value, len(kept)


def gt_path_length(dataset: Dataset, results: list[TrackResult]) -> float | None:
    """GT path length (m) from the first to the last frame the run processed; None without GT."""
    if not dataset.has_groundtruth or not results:
        return None
    assert dataset.gt_poses is not None
    covered = dataset.gt_poses[results[0].frame_index : results[-1].frame_index + 1]
    poses = covered[np.isfinite(covered).all(axis=(1, 2))]
    return float(PosePath3D(poses_se3=list(poses)).path_length) if len(poses) > 1 else 0.0
