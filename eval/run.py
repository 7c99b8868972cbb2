"""``symbio run``: stream a dataset through a frontend and measure its odometry.

Writes to ``--out DIR``:

* ``trajectory_tum.txt``: the pose of every tracked frame (TUM format). Poses of different map
  segments are in unrelated frames; the file does not separate them.
* ``keyframes_tum.txt``: the keyframes with their final poses (after the frontend's refinement).
* ``metrics.json``: ``dataset``, ``format``, ``frontend``, ``loop_closing`` (false for now),
  ``frames`` (given to the frontend), ``frames_tracked`` (with a pose), ``tracking_lost`` (state
  "lost"), ``frontend_failures`` (frames on which the frontend raised; they count as lost),
  ``images_skipped`` (did not decode), ``keyframes``, ``segments`` (that hold a tracked frame or
  keyframe), ``fps`` (frames per second of time spent inside the frontend), ``ate_rmse_before``
  (evo APE, translation RMSE, of the odometry after Sim(3) Umeyama alignment to the ground truth,
  over the frames of segment ``ate_segment`` (the one with most tracked frames) that have GT;
  ``ate_frames`` of them), ``path_length`` (GT path length in m over the frames the run covered)
  and ``interrupted``.
  Figures that need GT are null without it.

A frontend that raises on a frame costs only that frame: it is logged with the image path and
counted lost. When the run stops early (Ctrl-C, an unreadable image with --strict), whatever was
processed is still written before the error is re-raised.

Loop closing is not wired into ``symbio run`` yet: every run is odometry only. ``--no-loops``
says so explicitly (and keeps its meaning once loop closing lands); without it the run warns.

Examples:
  symbio run scene --no-loops --out run_vo                       # the mono-vo frontend
  symbio run scene --frontend replay --set trajectory=scene/groundtruth.txt --no-loops --out run_gt
  symbio run kitti/sequences/06 --frontend replay --set trajectory=orb.txt --set format=kitti \\
      --no-loops --out run_orb
"""

from __future__ import annotations

import argparse
import itertools
import logging
import time
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from evo.core import metrics
from evo.core.geometry import GeometryException
from evo.core.trajectory import PosePath3D, PoseTrajectory3D
from tqdm import tqdm

from frontends.base import FRONTENDS, Frontend, TrackResult
from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.datasets import Dataset, open_dataset
from frontends.datasets.cli import add_dataset_arguments
from frontends.errors import ConfigError
from frontends.trajectory_io import write_trajectory
from frontends.types import Frame, Keyframe

log = logging.getLogger(__name__)

TRAJECTORY_FILE = "trajectory_tum.txt"
KEYFRAMES_FILE = "keyframes_tum.txt"
METRICS_FILE = "metrics.json"


@dataclass
class OdometryRun:
    """What streaming frames through a frontend produced so far."""

    results: list[TrackResult] = field(default_factory=list)
    #: Position in ``results`` of each frame index (so backfilled results replace earlier ones).
    positions: dict[int, int] = field(default_factory=dict)
    frontend_failures: int = 0
    frontend_seconds: float = 0.0
    interrupted: bool = False

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


def track_frame(frontend: Frontend, frame: Frame, run: OdometryRun) -> TrackResult:
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


def stream_frames(frames: Iterable[Frame], frontend: Frontend, run: OdometryRun) -> None:
    for frame in frames:
        run.add(track_frame(frontend, frame, run))


def run_odometry(
    dataset: Dataset,
    frontend: Frontend,
    out_dir: Path,
    *,
    max_frames: int | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Stream ``dataset`` through ``frontend``, write trajectories and metrics to ``out_dir``.

    Returns the figures written to ``metrics.json``. If anything stops the run early (including
    KeyboardInterrupt), what was processed is written first and the exception re-raised.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    run = OdometryRun()
    total = len(dataset) if max_frames is None else min(max_frames, len(dataset))
    try:
        with tqdm(
            itertools.islice(dataset, max_frames),
            total=total,
            disable=not progress,
            unit="frame",
            desc=f"run {frontend.name}",
        ) as frames:
            stream_frames(frames, frontend, run)
    except BaseException:
        run.interrupted = True
        log.warning("run stopped after %d frames; writing what exists to %s", len(run.results), out_dir)
        write_outputs(out_dir, dataset, frontend, run)
        raise
    return write_outputs(out_dir, dataset, frontend, run)


def write_outputs(out_dir: Path, dataset: Dataset, frontend: Frontend, run: OdometryRun) -> dict[str, Any]:
    keyframes = frontend.keyframes()
    tracked = [(r.pose, r.timestamp) for r in run.results if r.pose is not None]
    write_poses(out_dir / TRAJECTORY_FILE, [pose for pose, _ in tracked], [stamp for _, stamp in tracked])
    write_poses(out_dir / KEYFRAMES_FILE, [k.pose for k in keyframes], [k.timestamp for k in keyframes])
    figures = run_figures(dataset, frontend, run, keyframes)
    write_json(out_dir / METRICS_FILE, figures)
    return figures


def write_poses(path: Path, poses: list[np.ndarray], timestamps: list[float]) -> None:
    if not poses:  # evo cannot build an empty trajectory; an empty file says "no poses" just as well
        path.write_text("", encoding="utf-8")
        return
    trajectory = PoseTrajectory3D(poses_se3=poses, timestamps=np.asarray(timestamps, dtype=np.float64))
    write_trajectory(path, trajectory, "tum")


def run_figures(
    dataset: Dataset, frontend: Frontend, run: OdometryRun, keyframes: list[Keyframe]
) -> dict[str, Any]:
    tracked = run.tracked
    segments = {r.segment for r in tracked} | {k.segment for k in keyframes}
    ate, ate_segment, ate_frames = odometry_ate(dataset, tracked)
    return {
        "dataset": str(dataset.root),
        "format": dataset.format_name,
        "frontend": frontend.name,
        "loop_closing": False,
        "frames": len(run.results),
        "frames_tracked": len(tracked),
        "tracking_lost": sum(r.state == "lost" for r in run.results),
        "frontend_failures": run.frontend_failures,
        "images_skipped": len(dataset.skipped),
        "keyframes": len(keyframes),
        "segments": len(segments),
        "fps": len(run.results) / run.frontend_seconds if run.frontend_seconds > 0 else None,
        "ate_rmse_before": ate,
        "ate_segment": ate_segment,
        "ate_frames": ate_frames,
        "path_length": gt_path_length(dataset, run.results),
        "interrupted": run.interrupted,
    }


def odometry_ate(dataset: Dataset, tracked: list[TrackResult]) -> tuple[float | None, int | None, int]:
    """evo APE (translation RMSE) after Sim(3) alignment, of the segment with most tracked frames.

    Returns (ATE or None, the segment aligned or None, frames used). Frames are matched to the GT
    by index; poses of different segments share no frame, so only one segment can be aligned.
    """
    if dataset.gt_poses is None or not tracked:
        return None, None, 0
    per_segment = Counter(r.segment for r in tracked)
    segment = min(per_segment, key=lambda s: (-per_segment[s], s))
    if len(per_segment) > 1:
        log.info(
            "%d map segments; ATE over segment %d (%d of %d tracked frames)",
            len(per_segment),
            segment,
            per_segment[segment],
            len(tracked),
        )
    pairs = [
        (r, dataset.gt_poses[r.frame_index])
        for r in tracked
        if r.segment == segment and np.isfinite(dataset.gt_poses[r.frame_index]).all()
    ]
    if len(pairs) < 3:  # a similarity transform needs three non-collinear positions
        log.warning("only %d tracked frames have ground truth; no ATE", len(pairs))
        return None, None, len(pairs)
    stamps = np.array([r.timestamp for r, _ in pairs])
    reference = PoseTrajectory3D(poses_se3=[gt for _, gt in pairs], timestamps=stamps)
    estimate = PoseTrajectory3D(poses_se3=[r.pose for r, _ in pairs], timestamps=stamps)
    try:
        estimate.align(reference, correct_scale=True)
    except GeometryException as exc:  # e.g. a frontend that never moved: Umeyama is degenerate
        log.warning("Sim(3) alignment to the ground truth failed (%s); no ATE", exc)
        return None, None, len(pairs)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((reference, estimate))
    return float(ape.get_statistic(metrics.StatisticsType.rmse)), segment, len(pairs)


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
        help="run a frontend over a dataset: trajectories and odometry metrics (loop closing: not yet)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_dataset_arguments(parser)
    parser.add_argument(
        "--frontend",
        default="mono-vo",
        help=f"frontend name ({', '.join(FRONTENDS.names())}; default mono-vo). "
        "replay takes its poses from a file: --set trajectory=FILE [--set format=kitti]",
    )
    parser.add_argument("--config", type=Path, help="YAML of the frontend's config")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a frontend config value (dotted keys for nested configs)",
    )
    parser.add_argument(
        "--no-loops",
        action="store_true",
        help="odometry only, no loop closing. Loop closing is not wired in yet, so runs are odometry "
        "only either way; without this flag the run says so with a warning",
    )
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder")
    parser.add_argument("--max-frames", type=int, metavar="N", help="stop after the first N frames")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_json_option(parser)
    parser.set_defaults(handler=run_command)


def run_command(args: argparse.Namespace) -> int:
    if args.max_frames is not None and args.max_frames < 1:
        raise ConfigError(f"--max-frames {args.max_frames}: must be at least 1")
    if not args.no_loops:
        log.warning("loop closing not wired yet; running odometry only (--no-loops silences this)")
    dataset = open_dataset(args.path, args.fmt, calib=args.calib, strict=args.strict)
    frontend = FRONTENDS.load(args.frontend)(dataset.camera, args.overrides, args.config)
    for note in dataset.notes:
        print(f"note: {note}")
    figures = run_odometry(
        dataset, frontend, args.out, max_frames=args.max_frames, progress=not args.no_progress
    )
    print(f"run {frontend.name} on {dataset.root} ({dataset.format_name})")
    print_figures(figures)
    print(f"wrote {args.out / TRAJECTORY_FILE}, {args.out / KEYFRAMES_FILE}, {args.out / METRICS_FILE}")
    write_json(args.json, figures)
    return 0
