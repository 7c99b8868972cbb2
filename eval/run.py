"""``symbio run``: stream a dataset through the SLAM pipeline and measure it.

frontend (each frame) -> object detector, loop detector (each keyframe) -> verifier -> backend
(``slam_backend.pipeline.LoopClosing``). Components are chosen by name (``--frontend``,
``--detector``, ``--object-detector``, ``--verifier``, ``--backend``) and configured by a run YAML
(``--config``: sections ``frontend``, ``detector``, ``object_detector``, ``verifier``, ``backend``,
``loop_closing``; each may name its component with ``name:``; a YAML without any section is the
frontend's own config) and by ``--set KEY=VALUE`` (a key starting with one of those section names
goes to that component, any other key to the frontend). ``--no-loops``: odometry only.

Writes to ``--out DIR``:

* ``trajectory_tum.txt``: every posed frame, loop-closed (each frame anchored to the backend's
  estimate of its keyframe); ``trajectory_odometry_tum.txt``: the same frames, odometry only;
  ``keyframes_tum.txt``: the loop-closed keyframes. Without loop closing the first equals the second.
* ``loops.csv``: every verified candidate: query, match (keyframe ids and frames), score, verified,
  inliers, accepted (the backend's final decision), scale, reason and, with GT poses, the
  constraint's rotation and translation-direction error against them (deg).
* ``metrics.json``: ``frames``, ``frames_tracked``, ``tracking_lost``, ``frames_initialising``
  (seen while a map initialised and not posed afterwards), ``frontend_failures``,
  ``frames_skipped`` (never given to the frontend: missing or undecodable images, duplicate or
  backwards timestamps) and ``frames_skipped_<cause>`` (per ``SKIP_CAUSES``), ``keyframes``,
  ``segments``, ``fps`` (frames per second of the whole pipeline),
  ``ms_per_frame_<stage>`` (frontend, objects, loop_detector, verifier, backend), ``ate_rmse_before`` /
  ``ate_rmse_after`` (evo APE translation RMSE after Sim(3) Umeyama alignment to the GT, odometry vs
  loop-closed, over the same frames: those of segment ``ate_segment``, the one with most tracked
  frames), ``ate_rmse_after_all`` (every posed frame; segments are one graph after loop closing),
  ``rpe_rmse_before`` / ``rpe_rmse_after`` (evo RPE translation over 1 s, on the aligned
  trajectories), ``loops_proposed`` (candidates verified), ``loops_verified``, ``loops_accepted``,
  ``false_loops_accepted`` (constraints that contradict the GT poses; see ``loop_truth``),
  ``loops_outside_gt_band``, ``lcd_precision`` / ``lcd_recall`` of the accepted loops against the GT
  loop pairs (``--tolerance`` frames), ``path_length`` (GT, m), ``interrupted``, the plugin
  failures (``object_detector_failures``, ``loop_detector_failures``, ``verifier_failures``,
  ``verifier_timeouts``) and, with ``--inject``, ``faults_injected_<kind>`` (per kind). Figures
  that need GT are null without it.

Checkpoint and resume: ``--checkpoint-every N`` saves the whole run state to ``DIR/checkpoint.json``
and ``DIR/checkpoint-FFFFFF.pkl`` every N frames (atomically; see ``eval.checkpoint``); after a
crash or ``kill -9``, ``symbio run --resume DIR`` continues with the stored dataset and options and
writes the outputs an uninterrupted run writes, bit for bit. While ``checkpoint.json`` exists the
run is unfinished: a checkpointed run deletes earlier outputs in DIR when it starts or resumes, and
its checkpoint once its outputs are written.

A frontend that raises on a frame costs only that frame (logged with the image path, counted lost);
failing object/loop detectors and verifiers cost one keyframe or candidate (counted), a verifier
past ``loop_closing.verify_timeout_s`` its candidate (reason "timeout"). ``--inject`` injects
faults to try this (``eval.inject``; README "What we test against"). When the run
stops early (Ctrl-C, an unreadable image with --strict), whatever was processed is written before
the error is re-raised.

Examples:
  symbio run scene --out run                                     # mono-vo + symbiolcd2 + pycolmap + gtsam
  symbio run scene --no-loops --out run_vo                       # odometry only
  symbio run scene --detector vbow --set detector.threshold=0.1 --out run_vbow
  symbio run scene --frontend replay --set trajectory=scene/groundtruth.txt --no-loops --out run_gt
  symbio run scene --inject corrupt-image:0.05,black:0.02,objects-raise --inject-seed 1 --out run_faults
  symbio run scene --checkpoint-every 50 --out run                # after a crash: symbio run --resume run
  symbio run kitti/sequences/06 --frontend replay --set trajectory=orb.txt --set format=kitti \\
      --no-loops --out run_orb
"""

from __future__ import annotations

import argparse
import csv
import itertools
import logging
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from evo.core import metrics
from evo.core.geometry import GeometryException
from evo.core.trajectory import PosePath3D, PoseTrajectory3D
from tqdm import tqdm

from eval import checkpoint
from eval.checkpoint import Checkpointer, CheckpointError, RunState
from eval.inject import KINDS, InjectedDataset, Injection, InjectionSpec
from eval.lcd_eval import default_object_detector
from eval.lcd_metrics import LoopPoseError, gt_references, has_reachable_loop, is_true_match, loop_pose_error
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
    FRONTENDS,
    CorrectableFrontend,
    Frontend,
    MaskingFrontend,
    SettlingFrontend,
    TrackResult,
    with_lookahead,
)
from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.config import config_to_dict, load_config, read_yaml_mapping
from frontends.datasets import Dataset, open_dataset
from frontends.datasets.base import SKIP_CAUSES
from frontends.datasets.cli import add_dataset_arguments
from frontends.errors import ConfigError
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
SECTIONS = ("frontend", "detector", "object_detector", "verifier", "backend", "loop_closing")
#: RPE is measured over this much time (s), a few keyframes at walking speed.
RPE_DELTA_S = 1.0


@dataclass(frozen=True)
class Components:
    """Names and settings of every part of the pipeline (``--config`` sections, ``--set``)."""

    frontend: str = "mono-vo"
    detector: str = "symbiolcd2"
    #: Empty: the oracle on synthetic scenes (they carry GT objects), ssd-mobilenet elsewhere.
    object_detector: str = ""
    verifier: str = "pycolmap"
    backend: str = "gtsam"
    #: Per section: ``key=value`` overrides (from the YAML file first, then the command line).
    overrides: dict[str, list[str]] = field(default_factory=dict)

    def of(self, section: str) -> list[str]:
        return self.overrides.get(section, [])


def _flatten(mapping: dict[str, Any], prefix: str = "") -> list[str]:
    """A YAML section as ``key=value`` overrides, each value dumped back to YAML."""
    items = []
    for key, value in mapping.items():
        if isinstance(value, dict):
            items += _flatten(value, f"{prefix}{key}.")
        else:
            # A scalar document ends with "..."; the override wants the value alone.
            dumped = yaml.safe_dump(value, default_flow_style=True).removesuffix("\n").removesuffix("\n...")
            items.append(f"{prefix}{key}={dumped}")
    return items


def load_components(
    config_path: Path | None, overrides: Sequence[str], names: dict[str, str | None]
) -> Components:
    """Components from a run YAML, ``--set`` overrides and the ``--frontend``/... name options."""
    chosen: dict[str, str] = {}
    per_section: dict[str, list[str]] = {section: [] for section in SECTIONS}
    if config_path is not None:
        mapping, _ = read_yaml_mapping(config_path)
        if any(key in SECTIONS for key in mapping):
            for key, value in mapping.items():
                if key not in SECTIONS:
                    raise ConfigError(f"{config_path}: unknown section {key!r} (expected one of {SECTIONS})")
                if not isinstance(value, dict):
                    raise ConfigError(f"{config_path}: section {key!r} must be a mapping")
                value = dict(value)
                if "name" in value:
                    chosen[key] = str(value.pop("name"))
                per_section[key] += _flatten(value)
        else:  # the frontend's own config file
            per_section["frontend"] += _flatten(mapping)
    for item in overrides:
        section, dot, rest = item.partition(".")
        if dot and section in SECTIONS:
            per_section[section].append(rest)
        else:
            per_section["frontend"].append(item)
    for section, name in names.items():
        if name is not None:
            chosen[section] = name
    known = {f.name for f in fields(Components)}
    return Components(**{k: v for k, v in chosen.items() if k in known}, overrides=per_section)


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
    out_dir: Path,
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
    the trajectories, loops and metrics to ``out_dir``; returns the figures of ``metrics.json``.

    ``checkpointer`` saves the state every N frames (deleted once the outputs are written);
    ``resume``: the state of a checkpoint (its ``frontend`` and ``closing`` must be the ones passed),
    whose processed frames are skipped. If anything stops the run early (including
    KeyboardInterrupt), what was processed is written first and the exception re-raised.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
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
        log.warning("run stopped after %d frames; writing what exists to %s", len(run.results), out_dir)
        closing.finish()
        write_outputs(out_dir, dataset, frontend, closing, run, tolerance, config or {}, viewer)
        raise
    figures = write_outputs(out_dir, dataset, frontend, closing, run, tolerance, config or {}, viewer)
    if run.results and all(r.pose is None for r in run.results):
        log.warning(
            "%s posed none of the %d frames: it never initialised. Likely causes: too little parallax "
            "(a camera that stands still or only rotates), too much motion between frames (a low frame "
            "rate or skipped frames), too few features (dark, blurred or textureless images), or wrong "
            "intrinsics",
            frontend.name, len(run.results),
        )  # fmt: skip
    if checkpointer is not None:
        checkpoint.discard(out_dir)
    return figures


def write_outputs(
    out_dir: Path,
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
    write_poses(out_dir / TRAJECTORY_FILE, [p for _, _, p in final], [t for _, t, _ in final])
    write_poses(out_dir / ODOMETRY_FILE, [p for _, _, p in odometry], [t for _, t, _ in odometry])
    keyframes = closing.keyframes
    corrected = closing.corrected_keyframe_poses()
    write_poses(
        out_dir / KEYFRAMES_FILE, [corrected[k.id] for k in keyframes], [k.timestamp for k in keyframes]
    )
    loops = closing.loops()
    write_loops_csv(out_dir / LOOPS_FILE, loops, loop_pose_errors(dataset, loops))
    figures = run_figures(dataset, frontend, closing, run, final, odometry, loops, tolerance)
    write_json(out_dir / METRICS_FILE, figures)
    images = write_plots(out_dir, dataset, odometry, final, loops, {k.id: k.frame_index for k in keyframes})
    write_report(out_dir, figures, config, images, loops)
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
        "dataset": str(dataset.root),
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
        **global_ba_figures(closing),
        "object_detector_failures": counters.object_detector_failures,
        "loop_detector_failures": counters.loop_detector_failures,
        "verifier_failures": counters.verifier_failures,
        "verifier_timeouts": counters.verifier_timeouts,
        **(dataset.injection.figures() if isinstance(dataset, InjectedDataset) else {}),
        "interrupted": run.interrupted,
        "checkpoints": run.checkpoints,
        "ms_per_checkpoint": 1e3 * run.checkpoint_seconds / run.checkpoints if run.checkpoints else None,
        "checkpoint_bytes": run.checkpoint_bytes if run.checkpoints else None,
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


def add_parser(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "run",
        help="run the SLAM pipeline over a dataset: trajectories, loops, ATE/RPE before and after",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_dataset_arguments(parser, path_optional=True)
    defaults = Components()
    parser.add_argument(
        "--frontend",
        help=f"frontend ({', '.join(FRONTENDS.names())}; default {defaults.frontend}). "
        "replay takes its poses from a file: --set trajectory=FILE [--set format=kitti]",
    )
    parser.add_argument(
        "--detector", help=f"loop detector ({', '.join(LOOP_DETECTORS.names())}; default {defaults.detector})"
    )
    parser.add_argument(
        "--object-detector",
        help=f"object detector ({', '.join(OBJECT_DETECTORS.names())}; default: oracle on synthetic "
        "scenes, ssd-mobilenet elsewhere)",
    )
    parser.add_argument("--verifier", help=f"verifier ({', '.join(VERIFIERS.names())}; default pycolmap)")
    parser.add_argument(
        "--backend", help=f"pose-graph backend ({', '.join(BACKENDS.names())}; default gtsam)"
    )
    parser.add_argument(
        "--config",
        type=Path,
        help=f"run YAML with sections {', '.join(SECTIONS)} (each may set name:), or a frontend config",
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a setting: SECTION.key=value for " + ", ".join(SECTIONS[1:]) + "; other keys "
        "(or frontend.key) go to the frontend",
    )
    parser.add_argument("--no-loops", action="store_true", help="odometry only, no loop closing")
    parser.add_argument(
        "--viewer",
        choices=["rerun"],
        help="log images, keypoints, objects, the three-tier graph, trajectories and loops to rerun: "
        "DIR/run.rrd, or a running viewer with --viewer-connect (optional extra symbiolcd2[viewer])",
    )
    parser.add_argument("--viewer-connect", metavar="URL", help="gRPC URL of a running rerun viewer")
    parser.add_argument(
        "--tolerance",
        type=int,
        default=3,
        help="frames an accepted loop may be off a GT reference (default 3)",
    )
    parser.add_argument("--out", type=Path, metavar="DIR", help="output folder (with --resume: DIR)")
    parser.add_argument("--max-frames", type=int, metavar="N", help="stop after the first N frames")
    parser.add_argument(
        "--checkpoint-every",
        type=int,
        metavar="N",
        help="save the whole run state to the output folder every N frames (atomically; deleted "
        "when the run ends) so that --resume can continue after a crash or kill",
    )
    parser.add_argument(
        "--resume",
        type=Path,
        metavar="DIR",
        help="continue the checkpointed run in DIR with its stored dataset and options (DATASET and "
        "options may be repeated but must match); the outputs equal an uninterrupted run's",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument(
        "--inject",
        metavar="KIND[:RATE],...",
        help="debug: inject faults into the run, RATE = fraction of frames or plugin calls hit. Kinds: "
        f"{', '.join(KINDS)} (see eval/inject.py and the README, 'What we test against')",
    )
    parser.add_argument(
        "--inject-seed", type=int, default=0, metavar="N", help="seed of the --inject choices (default 0)"
    )
    add_json_option(parser)
    parser.set_defaults(handler=lambda args: run_command(args, parser.get_default))


def describe(components: Components, closing: LoopClosing, args: argparse.Namespace) -> dict[str, Any]:
    """The run's configuration as the report shows it: component names, settings, options."""
    return {
        "dataset": str(args.path),
        "no_loops": args.no_loops,
        "tolerance": args.tolerance,
        "inject": args.inject,
        "inject_seed": args.inject_seed if args.inject else None,
        "components": {
            f.name: getattr(components, f.name) for f in fields(Components) if f.name != "overrides"
        },
        "overrides": components.overrides,
        "loop_closing": config_to_dict(closing.config),
    }


#: Options that do not change what a run computes: a resumed run may set them anew.
RESUME_FREE_OPTIONS = ("handler", "command", "verbose", "resume", "out", "json", "no_progress")
#: How the options whose name is not their destination are spelled in messages.
OPTION_NAMES = {"path": "DATASET", "fmt": "--format", "overrides": "--set"}


def resumed_options(
    args: argparse.Namespace, default: Callable[[str], Any], header: dict[str, Any]
) -> argparse.Namespace:
    """``args`` with the run options stored in the checkpoint; a conflicting option given on the
    command line is a CheckpointError (naming the header)."""
    assert args.resume is not None
    path = args.resume / checkpoint.HEADER_FILE
    if args.out is not None and args.out.resolve() != args.resume.resolve():
        raise CheckpointError(path, f"--out {args.out} differs from --resume {args.resume}")
    stored = header["spec"]
    given = checkpoint.run_spec(vars(args), RESUME_FREE_OPTIONS)
    for key, value in given.items():
        if value == checkpoint.run_spec({key: default(key)}, ())[key]:
            continue  # not given on this command line
        if stored.get(key) != value:
            option = OPTION_NAMES.get(key, "--" + key.replace("_", "-"))
            raise CheckpointError(
                path, f"the checkpoint was made with {option} {stored.get(key)!r}, not {value!r}"
            )
    resumed = argparse.Namespace(**vars(args))
    paths = set(stored["path_options"])
    for key, value in stored.items():
        if key not in ("components", "path_options"):
            setattr(resumed, key, Path(value) if key in paths and value is not None else value)
    resumed.out = args.resume
    return resumed


def run_command(args: argparse.Namespace, default: Callable[[str], Any] = lambda key: None) -> int:
    """``symbio run``; ``default`` gives the parser's default of an option (what --resume compares)."""
    header = checkpoint.read_header(args.resume) if args.resume is not None else None
    if header is not None:
        args = resumed_options(args, default, header)
    if args.path is None or args.out is None:
        raise ConfigError("symbio run: give DATASET and --out DIR (or --resume DIR)")
    if args.max_frames is not None and args.max_frames < 1:
        raise ConfigError(f"--max-frames {args.max_frames}: must be at least 1")
    if args.checkpoint_every is not None and args.checkpoint_every < 1:
        raise ConfigError(f"--checkpoint-every {args.checkpoint_every}: must be at least 1")
    if args.viewer is not None and (args.checkpoint_every is not None or header is not None):
        raise ConfigError("--viewer cannot be combined with --checkpoint-every or --resume")
    names = {
        "frontend": args.frontend,
        "detector": args.detector,
        "object_detector": args.object_detector,
        "verifier": args.verifier,
        "backend": args.backend,
    }
    components = load_components(args.config, args.overrides, names)
    spec = {
        **checkpoint.run_spec(vars(args), RESUME_FREE_OPTIONS),
        "components": checkpoint.run_spec(vars(components), ()),
        "path_options": sorted(k for k, v in vars(args).items() if isinstance(v, Path)),
    }
    if args.inject and (args.checkpoint_every is not None or header is not None):
        # The injected faults' counters and wrappers are a debugging harness, not run state.
        raise ConfigError("--inject cannot be combined with --checkpoint-every or --resume")
    injection = Injection(InjectionSpec.parse(args.inject, args.inject_seed)) if args.inject else None
    dataset: Dataset = open_dataset(args.path, args.fmt, calib=args.calib, strict=args.strict)
    if injection is not None:
        dataset = injection.wrap_dataset(dataset)
    checkpointer = None
    if args.checkpoint_every is not None:
        checkpointer = Checkpointer(args.out, args.checkpoint_every, spec, dataset)
    resume = None
    if header is None:
        checkpoint.discard(args.out)  # a stale checkpoint of another run must not be resumed
        frontend = FRONTENDS.load(components.frontend)(dataset.camera, components.of("frontend"))
        closing = build_loop_closing(dataset, None if args.no_loops else components)
        if injection is not None:
            injection.wrap_plugins(closing, dataset)
    else:
        if spec["components"] != header["spec"]["components"]:
            raise CheckpointError(
                args.out / checkpoint.HEADER_FILE,
                f"the run config ({args.config or '--set options'}) changed since the checkpoint was made",
            )
        checkpoint.check_dataset(header, dataset, args.out)
        images = checkpointer.images if checkpointer is not None else checkpoint.FrameImages()
        resume = checkpoint.load_state(header, args.out, dataset, images)
        frontend, closing = resume.frontend, resume.closing
        print(f"resuming {args.out} after {header['frames']} frames (next frame {resume.next_index})")
    for note in dataset.notes:
        print(f"note: {note}")
    if checkpointer is not None:
        for name in (*OUTPUT_FILES, TOP_VIEW_FILE, APE_FILE):  # outputs appear when the run ends
            (args.out / name).unlink(missing_ok=True)
    viewer = (
        RerunViewer(args.out / RRD_FILE, args.viewer_connect, camera=dataset.camera)
        if args.viewer == "rerun"
        else None
    )
    figures = run_odometry(
        dataset,
        frontend,
        args.out,
        loop_closing=closing,
        max_frames=args.max_frames,
        progress=not args.no_progress,
        tolerance=args.tolerance,
        config=describe(components, closing, args),
        viewer=viewer,
        checkpointer=checkpointer,
        resume=resume,
    )
    print(f"run {frontend.name} on {dataset.root} ({dataset.format_name})")
    print_figures(figures)
    print(f"wrote {', '.join(str(args.out / f) for f in OUTPUT_FILES)}")
    write_json(args.json, figures)
    return 0
