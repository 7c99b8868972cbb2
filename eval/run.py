"""A ``slam_backend.Slam`` run on a dataset, measured and written to an output folder: what
``symbio run``, ``symbio demo``, the benchmarks and ``eval table`` share (the command line is
``eval.run_cli``; its ``--help`` says what every output file holds).

The system itself (frontend -> object and loop detectors -> verifier -> backend, and the wiring
between them) is ``slam_backend.slam.Slam``; ``build_slam`` makes one from registered names
(``eval.components.Components``). ``run_odometry`` writes, into a claimed output folder
(``eval.outputs.RunFolder``), the loop-closed and odometry trajectories, the keyframes, ``loops.csv``,
the plots, ``report.html`` and last ``metrics.json`` (``complete`` true once everything else is in
place).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

import numpy as np
from evo.core import metrics
from evo.core.geometry import GeometryException
from evo.core.trajectory import PosePath3D
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
from frontends.base import TrackResult
from frontends.cli_common import flat_json
from frontends.config import load_config
from frontends.datasets import Dataset
from frontends.datasets.base import SKIP_CAUSES, ReadAhead
from frontends.errors import display_path
from frontends.types import Frame
from slam_backend.pipeline import LoopClosing, LoopClosingConfig, LoopRecord
from slam_backend.slam import (
    KEYFRAMES_FILE,
    LOOPS_FILE,
    ODOMETRY_FILE,
    TRAJECTORY_FILE,
    Slam,
    SlamResult,
    SlamState,
    largest_segment,
    write_loops_csv,
    write_poses,
)

log = logging.getLogger(__name__)

METRICS_FILE = "metrics.json"
RRD_FILE = "run.rrd"
OUTPUT_FILES = (TRAJECTORY_FILE, ODOMETRY_FILE, KEYFRAMES_FILE, LOOPS_FILE, METRICS_FILE, REPORT_FILE)
#: RPE is measured over this much time (s), a few keyframes at walking speed.
RPE_DELTA_S = 1.0


def attach_viewer(viewer: RerunViewer, closing: LoopClosing) -> None:
    """Keyframes (with objects and the detector's graph) and loops go to the viewer as they happen."""
    closing.on_keyframe = viewer.keyframe
    closing.on_loop = lambda record: viewer.loop(
        record, closing.keyframe(record.query).pose, closing.keyframe(record.match).pose
    )


def build_slam(dataset: Dataset, components: Components | None, *, loops: bool = True) -> Slam:
    """The system of ``components`` (default: ``Components()``) for ``dataset``'s camera;
    ``loops=False`` (``--no-loops``): odometry only, the backend holding the keyframe chain. The
    object detector defaults to the oracle on synthetic scenes (their GT objects), else the CNN."""
    c = components or Components()
    return Slam(
        dataset.camera,
        frontend=c.frontend,
        loop_detector=c.detector if loops else None,
        object_detector=c.object_detector or default_object_detector(dataset),
        verifier=c.verifier,
        backend=c.backend,
        loop_closing=load_config(LoopClosingConfig, None, c.of("loop_closing")),
        overrides={
            part: c.of(part) for part in ("frontend", "detector", "object_detector", "verifier", "backend")
        },
    )


def run_odometry(
    dataset: Dataset,
    slam: Slam,
    out: Path | RunFolder,
    *,
    max_frames: int | None = None,
    progress: bool = True,
    tolerance: int = 0,
    config: dict[str, Any] | None = None,
    viewer: RerunViewer | None = None,
    checkpointer: Checkpointer | None = None,
    resume: RunState | None = None,
    on_frame: Callable[[Frame, TrackResult], None] | None = None,
) -> dict[str, Any]:
    """Stream ``dataset`` through ``slam`` (``build_slam``, or ``Slam.from_parts`` for a restored
    run), write the trajectories, loops and metrics to ``out``; returns the figures of ``metrics.json``.

    ``out``: a claimed ``RunFolder``, or a folder path that is claimed for the call (refused when it
    holds files symbio did not write, or another command is writing there: see ``eval.outputs``).

    ``checkpointer`` saves the state every N frames (deleted once the outputs are written);
    ``resume``: the state of a checkpoint (``slam`` must be built from its parts), whose processed
    frames are skipped. If anything stops the run early (including KeyboardInterrupt), what was
    processed is written first and the exception re-raised. ``on_frame`` runs after every frame,
    outside the run's timings (``eval.bench.long`` samples the run with it).
    """
    with contextlib.ExitStack() as stack:
        folder = out if isinstance(out, RunFolder) else stack.enter_context(run_folder(out))
        return _run_into(
            folder, dataset, slam, max_frames, progress, tolerance, config, viewer, checkpointer, resume,
            on_frame,
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
    slam: Slam,
    max_frames: int | None,
    progress: bool,
    tolerance: int,
    config: dict[str, Any] | None,
    viewer: RerunViewer | None,
    checkpointer: Checkpointer | None,
    resume: RunState | None,
    on_frame: Callable[[Frame, TrackResult], None] | None = None,
) -> dict[str, Any]:
    if viewer is not None:
        attach_viewer(viewer, slam.closing)
    state = slam.state
    total = len(dataset) if max_frames is None else min(max_frames, len(dataset))
    # Frames decode in a thread while the previous one is tracked (frontends.datasets.base.ReadAhead).
    reader = ReadAhead(
        itertools.islice(dataset, max_frames)
        if resume is None
        else checkpoint.remaining(dataset, max_frames, resume)
    )
    stream: Iterable[Frame] = reader
    if checkpointer is not None:
        stream = checkpointer.track(stream)

    # The last frame tracked: with_lookahead reads a few frames ahead of it.
    reached = -1 if resume is None else resume.next_index - 1

    def after_frame(frame: Frame, result: TrackResult) -> None:
        nonlocal reached
        reached = frame.index
        if viewer is not None:
            viewer.frame(frame, result)
        if checkpointer is not None:
            checkpointer.after_frame(frame, slam.frontend, slam.closing, state)
        if on_frame is not None:
            on_frame(frame, result)

    try:
        with tqdm(
            stream,
            total=total,
            initial=len(state.results),
            disable=not progress,
            unit="frame",
            desc=f"run {slam.frontend.name}",
        ) as frames:
            result = slam.run(frames, after_frame)
    except BaseException:
        reader.close()
        if not reader.finished:  # what was read ahead was never tracked: those skips are not the run's
            dataset.forget_skips_after(reached)
        state.interrupted = True
        log.warning("run stopped after %d frames; writing what exists to %s", len(state.results), folder.root)
        write_outputs(folder, dataset, slam.finish(), state, tolerance, config or {}, viewer)
        raise
    finally:
        reader.close()
    figures = write_outputs(folder, dataset, result, state, tolerance, config or {}, viewer)
    if state.results and all(r.pose is None for r in state.results):
        log.warning(
            "%s posed none of the %d frames: it never initialised. Likely causes: too little parallax "
            "(a camera that stands still or only rotates), too much motion between frames (a low frame "
            "rate or skipped frames), too few features (dark, blurred or textureless images), or wrong "
            "intrinsics",
            slam.frontend.name, len(state.results),
        )  # fmt: skip
    if checkpointer is not None:
        checkpoint.discard(folder.root)
    return figures


def write_outputs(
    folder: RunFolder,
    dataset: Dataset,
    result: SlamResult,
    state: SlamState,
    tolerance: int,
    config: dict[str, Any],
    viewer: RerunViewer | None = None,
) -> dict[str, Any]:
    if viewer is not None:
        viewer.trajectories(result.trajectory, result.odometry)
        viewer.close()
    with folder.atomic(TRAJECTORY_FILE) as path:
        write_poses(path, result.trajectory)
    with folder.atomic(ODOMETRY_FILE) as path:
        write_poses(path, result.odometry)
    keyframes = result.keyframes
    with folder.atomic(KEYFRAMES_FILE) as path:
        write_poses(path, [(k.frame_index, k.timestamp, result.keyframe_poses[k.id]) for k in keyframes])
    with folder.atomic(LOOPS_FILE) as path:
        write_loops_csv(path, result.loops, loop_pose_errors(dataset, result.loops))
    figures = run_figures(dataset, result, state, tolerance)
    images = write_plots(
        folder,
        dataset,
        result.odometry,
        result.trajectory,
        result.loops,
        {k.id: k.frame_index for k in keyframes},
    )
    write_report(folder, figures, config, images, result.loops)
    # Last: a metrics.json that says "complete" means every other output above is in place.
    folder.write_text(METRICS_FILE, flat_json(figures))
    return figures


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


def run_figures(dataset: Dataset, result: SlamResult, state: SlamState, tolerance: int) -> dict[str, Any]:
    """``result.figures`` with the dataset's: ATE/RPE against its GT, skipped frames, injected
    faults, loop truth, and the run's checkpoints."""
    segment = largest_segment(state)
    in_segment = {r.frame_index for r in state.tracked if r.segment == segment}
    before = trajectory_errors(dataset, [p for p in result.odometry if p[0] in in_segment])
    after = trajectory_errors(dataset, [p for p in result.trajectory if p[0] in in_segment])
    after_all = trajectory_errors(dataset, result.trajectory)
    own = result.figures
    figures: dict[str, Any] = {
        "dataset": display_path(dataset.root),
        "format": dataset.format_name,
        **own,
        "frames_skipped": len(dataset.skipped),
        **{
            f"frames_skipped_{cause.replace(' ', '_')}": sum(s.cause == cause for s in dataset.skipped)
            for cause in SKIP_CAUSES
        },
        "ate_rmse_before": before[0],
        "ate_rmse_after": after[0],
        "ate_rmse_after_all": after_all[0],
        "rpe_rmse_before": before[1],
        "rpe_rmse_after": after[1],
        "ate_segment": segment if before[0] is not None else None,
        "ate_frames": before[2],
        "path_length": gt_path_length(dataset, state.results),
        **(dataset.injection.figures() if isinstance(dataset, InjectedDataset) else {}),
        "interrupted": state.interrupted,
        # metrics.json is written after every other output: true means all of them are in place.
        "complete": not state.interrupted,
        "checkpoints": state.checkpoints,
        "ms_per_checkpoint": 1e3 * state.checkpoint_seconds / state.checkpoints
        if state.checkpoints
        else None,
        "checkpoint_bytes": state.checkpoint_bytes if state.checkpoints else None,
        "checkpoint_failures": state.checkpoint_failures,
    }
    figures.update(loop_truth(dataset, result.loops, result.keyframes, tolerance))
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
