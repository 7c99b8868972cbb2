"""Long runs: cost per frame along the run, memory, end-of-run work, and what loop closing buys on
minutes of video (issue 42).

A synthetic 640x480 scene of ``--frames`` frames at 30 fps (``symbio synth``, cached under
``--work``; 9 000 frames = 5 min) goes through ``symbio run``'s pipeline with the default components
(as ``eval.bench.pipeline``: mono-vo, symbiolcd2 with the oracle object detector at 30 % misses,
pycolmap, gtsam PCM + GNC), sampled after every frame: wall and CPU time, the stage timers of the
frontend and of loop closing (``loops.verifier`` is the verification worker's time, which overlaps
tracking: ``loop_closing.overlap_verification``), keyframes and map points; a thread reads the
resident set size every 50 ms, so the end-of-run bundle adjustment's peak is seen too. A second run
without loop closing, with the same movable-object masks, gives the baseline ATE ("masked no-loops").

Printed: per decile of the frames, ms per frame (wall, CPU and by stage), keyframes, map points and
RSS at its end; then ATE before / after / masked no-loops, loops accepted / false, run and end-of-run
seconds. With ``--kitti00`` (default: ``$SYMBIO_SHARED/data/trajectories/KITTI_00_gt.txt`` when it
is there) also the 4 541 poses of KITTI 00 as a monocular pose graph (``symbio posegraph
--trajectory ... --simulate mono-drift``): its loops, ATE and time.

``--json`` writes the figures as one flat object, e.g. ``ms_per_frame_ratio_last_to_second_decile``,
``fps``, ``peak_rss_mb``, ``end_of_run_seconds``, ``run_seconds``, ``ate_rmse_before``,
``ate_rmse_after``, ``ate_rmse_masked_no_loops``, ``loops_accepted``, ``false_loops_accepted`` and
per decile ``decile_<k>_ms_per_frame`` etc. Targets (issue 42, 9 000 frames on 2 cores): last decile
<= 1.15 x the second, >= 25 frames/s, peak RSS <= 1.5 GB, end of run <= 10 % of the run, ATE after
<= 0.5 x masked no-loops, no false loop; missed ones are listed at the end.

Usage: ``python -m eval.bench_long --frames 9000 --trajectory loop --seed 1 --json OUT``.
"""

from __future__ import annotations

import argparse
import logging
import os
import resource
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from eval.bench.pipeline import run_scene
from eval.bench.scenes import scene_folder
from frontends.base import TrackResult
from frontends.cli_common import add_json_option, add_set_option, write_json
from frontends.errors import ConfigError, InputFileError
from frontends.trajectory_io import read_kitti_poses, read_times
from frontends.types import Frame, Trajectory
from slam_backend.slam import Slam

DECILES = 10
#: The targets of issue 42 (9 000 frames, 2 cores).
MAX_DECILE_RATIO = 1.15
MIN_FPS = 25.0
MAX_PEAK_RSS_MB = 1500.0
MAX_END_OF_RUN_SHARE = 0.10
MAX_AFTER_TO_MASKED = 0.5
TRAJECTORIES = ("loop", "figure8", "out-and-back")
#: Figures of the full run taken as they are.
RUN_KEYS = (
    "ate_rmse_before", "ate_rmse_after", "ate_rmse_after_all", "loops_proposed", "loops_verified",
    "loops_accepted", "false_loops_accepted", "loops_outside_gt_band",
)  # fmt: skip
#: Figures printed after the decile table.
SUMMARY_KEYS = (
    "frames", "frames_tracked", "segments", "keyframes", "fps", "run_seconds", "end_of_run_seconds",
    "end_of_run_share", "peak_rss_mb", "ms_per_frame_ratio_last_to_second_decile", "ate_rmse_before",
    "ate_rmse_after", "ate_rmse_after_all", "ate_rmse_masked_no_loops", "loops_proposed", "loops_accepted",
    "false_loops_accepted",
)  # fmt: skip


def rss_mb() -> float:
    """This process's resident set size now (MB), from ``/proc``; the peak so far where there is none."""
    try:
        with open("/proc/self/statm", "rb") as statm:
            return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB


class RssSampler:
    """Reads the RSS every ``period`` seconds on a thread while it is running (``with``)."""

    def __init__(self, period: float = 0.05) -> None:
        self.period = period
        self.peak = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, name="rss-sampler", daemon=True)

    def _sample(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, rss_mb())
            self._stop.wait(self.period)

    def __enter__(self) -> RssSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, rss_mb())


@dataclass
class Sample:
    """The run's state after one frame."""

    frame: int
    wall: float
    cpu: float
    #: Cumulative seconds per stage: ``frontend.<stage>`` and ``loops.<stage>``.
    stages: dict[str, float]
    keyframes: int
    map_points: int
    rss_mb: float


def stage_seconds(slam: Slam) -> dict[str, float]:
    """Cumulative seconds per stage of the frontend (if it keeps ``stage_seconds``) and loop closing."""
    frontend = getattr(slam.frontend, "stage_seconds", {})
    stages = {f"frontend.{k}": float(v) for k, v in frontend.items()}
    stages["frontend"] = slam.state.frontend_seconds
    stages.update({f"loops.{k}": float(v) for k, v in slam.closing.counters.seconds.items()})
    return stages


def map_points(slam: Slam) -> int:
    """Alive points of the frontend's current map segment (0 for a frontend without one)."""
    segment_map = getattr(slam.frontend, "segment_map", None)
    points = getattr(segment_map, "points", None)
    alive = getattr(points, "alive", None)
    return int(np.count_nonzero(alive)) if alive is not None else 0


@dataclass
class Probe:
    """Samples a run at the end of every decile of its frames (``on_frame``)."""

    slam: Slam
    frames: int
    samples: list[Sample] = field(default_factory=list)
    started: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        self.ends = {min(self.frames, round(self.frames * (k + 1) / DECILES)) - 1 for k in range(DECILES)}
        self.started = (time.perf_counter(), time.process_time())

    def on_frame(self, frame: Frame, result: TrackResult) -> None:
        # Nothing per frame but this test: the peak RSS is the sampler thread's (RssSampler).
        if frame.index not in self.ends:
            return
        self.samples.append(
            Sample(
                frame.index,
                time.perf_counter(),
                time.process_time(),
                stage_seconds(self.slam),
                len(self.slam.closing.keyframes),
                map_points(self.slam),
                rss_mb(),
            )
        )


def decile_rows(probe: Probe) -> list[dict[str, Any]]:
    """Per decile: frames, ms per frame (wall, CPU, by stage); keyframes, map points, RSS at its end."""
    rows = []
    wall0, cpu0 = probe.started
    previous = Sample(-1, wall0, cpu0, {}, 0, 0, 0.0)
    for sample in probe.samples:
        count = sample.frame - previous.frame
        per = 1e3 / max(count, 1)
        rows.append(
            {
                "frames": count,
                "ms_per_frame": (sample.wall - previous.wall) * per,
                "cpu_ms_per_frame": (sample.cpu - previous.cpu) * per,
                **{
                    f"ms_{stage}": (seconds - previous.stages.get(stage, 0.0)) * per
                    for stage, seconds in sorted(sample.stages.items())
                },
                "keyframes": sample.keyframes,
                "map_points": sample.map_points,
                "rss_mb": sample.rss_mb,
            }
        )
        previous = sample
    return rows


def run_long(
    folder: Path, out: Path, overrides: Sequence[str] = (), baseline: bool = True
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The full run of the scene in ``folder`` (sampled) and, with ``baseline``, the masked run
    without loop closing: (flat figures, decile rows)."""
    probes: list[Probe] = []
    frames = len(list((folder / "rgb").iterdir()))

    def start(slam: Slam) -> Callable[[Frame, TrackResult], None]:
        probes.append(Probe(slam, frames))
        return probes[-1].on_frame

    started = time.perf_counter()
    with RssSampler() as sampler:
        figures = run_scene(folder, out / "full", "full", overrides, on_start=start)
    probe = probes[0]
    rows = decile_rows(probe)
    last_frame_wall = probe.samples[-1].wall if probe.samples else started
    slam = probe.slam
    run_seconds = slam.state.total_seconds
    result: dict[str, Any] = {
        "frames": frames,
        "frames_tracked": figures.get("frames_tracked"),
        "segments": figures.get("segments"),
        "keyframes": figures.get("keyframes"),
        "run_seconds": run_seconds,
        "wall_seconds": time.perf_counter() - started,
        "fps": frames / run_seconds if run_seconds > 0 else None,
        "end_of_run_seconds": slam.state.finish_seconds,
        "end_of_run_share": slam.state.finish_seconds / run_seconds if run_seconds > 0 else None,
        "after_last_frame_seconds": time.perf_counter() - last_frame_wall,
        "peak_rss_mb": sampler.peak,
        "ms_per_frame_ratio_last_to_second_decile": (
            rows[-1]["ms_per_frame"] / rows[1]["ms_per_frame"]
            if len(rows) >= 2 and rows[1]["ms_per_frame"]
            else None
        ),
        "cpu_ms_per_frame_ratio_last_to_second_decile": (
            rows[-1]["cpu_ms_per_frame"] / rows[1]["cpu_ms_per_frame"]
            if len(rows) >= 2 and rows[1]["cpu_ms_per_frame"]
            else None
        ),
        **{key: figures.get(key) for key in RUN_KEYS},
    }
    if baseline:
        masked = run_scene(folder, out / "masked_no_loops", "masked", overrides)
        result["ate_rmse_masked_no_loops"] = masked.get("ate_rmse_after_all")
    for k, row in enumerate(rows, start=1):
        result.update({f"decile_{k}_{key}": value for key, value in row.items()})
    return result, rows


def read_kitti00(path: Path) -> Trajectory:
    """KITTI poses (with ``<stem>_times.txt`` beside them if there), read before the long run so a
    bad file is an error at once (``TrajectoryFileError`` naming it)."""
    times = path.with_name(f"{path.stem}_times.txt")
    return read_kitti_poses(path, read_times(times) if times.is_file() else None)


def kitti00_posegraph(trajectory: Trajectory, name: str, seed: int) -> dict[str, Any]:
    """KITTI 00's ground truth as a monocular Sim(3) pose graph (``symbio posegraph --trajectory PATH
    --format kitti --simulate mono-drift --seed S``): poses, loops, ATE, seconds."""
    from frontends.config import load_config
    from slam_backend.experiment import figures, run_problem
    from slam_backend.posegraph import BackendConfig
    from slam_backend.simulate import MonoDriftConfig, simulate_mono_drift

    problem = simulate_mono_drift(trajectory, MonoDriftConfig(seed=seed), name=f"{name} mono-drift")
    config = load_config(BackendConfig, None, [f"mode={problem.mode}"])
    start = time.perf_counter()
    result = run_problem(problem, config)
    seconds = time.perf_counter() - start
    measured = figures(problem, result)
    return {
        "kitti00_poses": len(problem.keyframe_ids),
        "kitti00_seconds": seconds,
        **{f"kitti00_{k}": v for k, v in measured.items() if isinstance(v, (int, float)) or v is None},
    }


def check_targets(figures: dict[str, Any]) -> list[str]:
    failures = []
    ratio = figures.get("ms_per_frame_ratio_last_to_second_decile")
    if ratio is not None and ratio > MAX_DECILE_RATIO:
        failures.append(f"last decile {ratio:.2f} x the second > {MAX_DECILE_RATIO}")
    if figures.get("fps") is not None and figures["fps"] < MIN_FPS:
        failures.append(f"{figures['fps']:.1f} frames/s < {MIN_FPS:.0f}")
    if figures["peak_rss_mb"] > MAX_PEAK_RSS_MB:
        failures.append(f"peak RSS {figures['peak_rss_mb']:.0f} MB > {MAX_PEAK_RSS_MB:.0f}")
    share = figures.get("end_of_run_share")
    if share is not None and share > MAX_END_OF_RUN_SHARE:
        failures.append(f"end of run {100 * share:.0f} % of the run > {100 * MAX_END_OF_RUN_SHARE:.0f} %")
    after, masked = figures.get("ate_rmse_after_all"), figures.get("ate_rmse_masked_no_loops")
    if after is not None and masked and after > MAX_AFTER_TO_MASKED * masked:
        failures.append(f"ATE after {after:.4f} > {MAX_AFTER_TO_MASKED} x masked no-loops {masked:.4f}")
    if figures.get("false_loops_accepted"):
        failures.append(f"{figures['false_loops_accepted']} false loops accepted")
    return failures


def print_report(name: str, figures: dict[str, Any], rows: list[dict[str, Any]]) -> None:
    stages = sorted({k for row in rows for k in row if k.startswith("ms_") and k != "ms_per_frame"})
    print(f"\n{name}: per decile of the frames (ms per frame; keyframes, map points, RSS at its end)")
    header = [
        "decile",
        "frames",
        "ms/frame",
        "cpu ms/frame",
        *[s[3:] for s in stages],
        "keyframes",
        "points",
        "RSS MB",
    ]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for k, row in enumerate(rows, start=1):
        cells = [
            str(k), str(row["frames"]), f"{row['ms_per_frame']:.1f}", f"{row['cpu_ms_per_frame']:.1f}",
            *[f"{row.get(s, 0.0):.1f}" for s in stages],
            str(row["keyframes"]), str(row["map_points"]), f"{row['rss_mb']:.0f}",
        ]  # fmt: skip
        print("| " + " | ".join(cells) + " |")
    print()
    for key in SUMMARY_KEYS:
        if key in figures:
            value = figures[key]
            print(f"  {key:44s} {value:.4g}" if isinstance(value, float) else f"  {key:44s} {value}")
    kitti = {k: v for k, v in figures.items() if k.startswith("kitti00_")}
    for key, value in kitti.items():
        print(f"  {key:44s} {value:.4g}" if isinstance(value, float) else f"  {key:44s} {value}")


def default_kitti00() -> Path | None:
    shared = Path(os.environ.get("SYMBIO_SHARED", "../shared"))
    path = shared / "data" / "trajectories" / "KITTI_00_gt.txt"
    return path if path.is_file() else None


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=9000, help="frames of the scene (30 fps; default 9000)")
    parser.add_argument("--trajectory", choices=TRAJECTORIES, default="loop")
    parser.add_argument(
        "--seed", type=int, default=1, help="seed of the scene and of the KITTI 00 simulation"
    )
    parser.add_argument("--work", type=Path, help="scene cache and run outputs (default: a temporary folder)")
    parser.add_argument("--no-baseline", action="store_true", help="skip the masked run without loop closing")
    parser.add_argument(
        "--kitti00",
        type=Path,
        help="KITTI 00 GT poses for the pose-graph part (default: from ../shared if there)",
    )
    parser.add_argument("--no-kitti00", action="store_true", help="skip the KITTI 00 pose graph")
    add_set_option(parser, "override a setting of the runs as in `symbio run --set` (repeatable)")
    add_json_option(parser)
    args = parser.parse_args(argv)
    if args.frames < 2 * DECILES:
        parser.error(f"--frames must be >= {2 * DECILES}")
    logging.basicConfig(level=logging.ERROR)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_long_"))
    name = f"{args.trajectory}_{args.seed}_{args.frames}"
    kitti = None if args.no_kitti00 else (args.kitti00 or default_kitti00())
    try:
        kitti_poses = read_kitti00(kitti) if kitti is not None else None
        folder = scene_folder(work, args.trajectory, args.seed, args.frames)
        figures, rows = run_long(folder, work / "runs" / name, args.overrides, not args.no_baseline)
    except (ConfigError, InputFileError) as error:  # a bad --set (the first run) or --kitti00 file
        parser.error(str(error))
    figures = {"trajectory": args.trajectory, "seed": args.seed, **figures}
    if kitti is not None and kitti_poses is not None:
        figures.update(kitti00_posegraph(kitti_poses, kitti.name, args.seed))
    print_report(name, figures, rows)
    for failure in check_targets(figures):
        print(f"target missed: {failure}")
    if args.json:
        write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
