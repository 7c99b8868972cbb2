"""Benchmark of the whole SLAM pipeline on synthetic scenes: loop closing's effect, false loops, speed.

For every (trajectory, seed) — by default loop, figure8 and out-and-back with seeds 0, 1, 2, plus
the no-revisit control ``none`` — a 20 s 640x480 scene is rendered (cached under ``--work``) and
run through ``symbio run``'s pipeline with the default components (mono-vo, symbiolcd2 with the
oracle object detector at 30 % misses, pycolmap, gtsam PCM+GNC). One run per scene, sequential, so
the frames per second are those of one process on an otherwise idle machine.

The table gives ATE (evo, Sim(3)-aligned) of two runs without loop closing (``symbio run
--no-loops``, and the same with the full run's object detector masking movable objects, which
changes the frontend's map), and of the full run before (its odometry chain) and after loop
closing, loops proposed / verified / accepted / false (constraints off the GT relative pose:
``eval.run.loop_truth``) / outside the GT labeller's band (by more than 3 frames; right constraints
between views of the same wall 1-2 m apart land there), segments and pipeline fps. The frontend
continues from every loop-corrected map, so the full run's own odometry already profits from the
loops; "after / masked no loops" is what loop closing buys (the runs differ only in loop closing).
ATE "no loops", "masked" and "after" are over every posed frame (``ate_rmse_after_all``): when the
frontend lost tracking, the segments of a run without loops are joined by the loose identity link
(placed where the last pose was) and loop closing is what places them, so a per-segment ATE would
hide what it buys. "before (segment)" and "after/before" are the run's own ``ate_rmse_before`` /
``ate_rmse_after``, over the segment with most frames (equal to the others with one segment).
Targets checked at the end: ``after <= 0.5 x masked no loops`` on every revisiting scene, no false
loop anywhere, no loop on the control, >= 20 fps.

Usage: ``python -m eval.bench.pipeline [--trajectories loop,figure8,out-and-back] [--seeds 0,1,2]
[--frames 600] [--work DIR] [--set SECTION.key=value ...] [--json OUT]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from eval.bench.scenes import parse_seeds, scene_folder
from eval.components import load_components
from eval.demo import synthetic_components
from eval.run import build_slam, run_odometry
from frontends.base import TrackResult
from frontends.cli_common import add_json_option, add_set_option, write_json
from frontends.datasets import open_dataset
from frontends.errors import ConfigError
from frontends.types import Frame
from slam_backend.pipeline import LoopClosing
from slam_backend.slam import Slam

CONTROL = "none"
KEYS = (
    "ate_rmse_before", "ate_rmse_after", "ate_rmse_after_all", "loops_proposed", "loops_verified",
    "loops_accepted", "false_loops_accepted", "loops_outside_gt_band", "fps", "frames_tracked", "segments",
)  # fmt: skip


def run_scene(
    folder: Path,
    out: Path,
    mode: str = "full",
    overrides: Sequence[str] = (),
    on_start: Callable[[Slam], Callable[[Frame, TrackResult], None]] | None = None,
) -> dict[str, Any]:
    """``full``: the pipeline; ``plain``: odometry only (``symbio run --no-loops``); ``masked``:
    odometry only with the same object detector masking movable objects as the full run.
    ``overrides``: ``symbio run --set`` items (a key without a section goes to the frontend).
    ``on_start(slam)``, if given, returns what runs after every frame (``run_odometry``'s ``on_frame``)."""
    dataset = open_dataset(folder)
    defaults = synthetic_components()
    extra = load_components(None, overrides, {})
    components = dataclasses.replace(
        defaults,
        overrides={s: [*defaults.of(s), *extra.of(s)] for s in {*defaults.overrides, *extra.overrides}},
    )
    slam = build_slam(dataset, components, loops=mode != "plain")
    if mode == "masked":
        closing = slam.closing
        masked = LoopClosing(closing.backend, objects=closing.objects, config=closing.config)
        slam = Slam.from_parts(slam.frontend, masked)
    on_frame = on_start(slam) if on_start is not None else None
    return run_odometry(dataset, slam, out, progress=False, tolerance=3, on_frame=on_frame)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trajectories", default="loop,figure8,out-and-back")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--work", type=Path, help="scene cache and run outputs (default: a temporary folder)")
    add_set_option(parser, "override a setting of every run as in `symbio run --set` (repeatable)")
    add_json_option(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_pipeline_"))
    seeds = parse_seeds(args.seeds)
    jobs = [(t, s) for t in args.trajectories.split(",") for s in seeds] + [(CONTROL, seeds[0])]
    try:
        rows = _run_all(jobs, work, args.frames, args.overrides)
    except ConfigError as error:  # a bad --set, raised by the first run
        parser.error(str(error))
    print_table(rows)
    failures = check_targets(rows)
    for failure in failures:
        print(f"target missed: {failure}")
    if args.json:
        write_json(args.json, {f"{n}_{k}": v for n, row in rows.items() for k, v in row.items()})
    return 0


def _run_all(
    jobs: list[tuple[str, int]], work: Path, frames: int, overrides: Sequence[str]
) -> dict[str, dict[str, Any]]:
    """Full, plain and masked runs of every (trajectory, seed): the table's rows."""
    rows: dict[str, dict[str, Any]] = {}
    for trajectory, seed in jobs:
        name = f"{trajectory}_{seed}"
        folder = scene_folder(work, trajectory, seed, frames)
        figures = run_scene(folder, work / "runs" / name, "full", overrides)
        rows[name] = {key: figures.get(key) for key in KEYS}
        # The frontend continues from each loop-corrected map, so the same run's odometry chain
        # already benefits from the loops: the honest baseline is a run without loop closing.
        baseline = run_scene(folder, work / "runs" / f"{name}_no_loops", "plain", overrides)
        rows[name]["ate_rmse_no_loops"] = baseline["ate_rmse_after_all"]
        masked = run_scene(folder, work / "runs" / f"{name}_masked_no_loops", "masked", overrides)
        rows[name]["ate_rmse_masked_no_loops"] = masked["ate_rmse_after_all"]
        print(name, {k: rows[name][k] for k in KEYS}, flush=True)
    return rows


def print_table(rows: dict[str, dict[str, Any]]) -> None:
    print(
        "\n| scene | ATE no loops | ATE no loops, masked | ATE after | after/no loops | "
        "after/masked no loops | ATE before (segment) | after/before (segment) | proposed | verified | "
        "accepted | false | outside GT band | segments | fps |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        none, masked, after = r["ate_rmse_no_loops"], r["ate_rmse_masked_no_loops"], r["ate_rmse_after_all"]
        before, after_segment = r["ate_rmse_before"], r["ate_rmse_after"]
        print(
            f"| {name} | {_f(none)} | {_f(masked)} | {_f(after)} | {_ratio(after, none)} | "
            f"{_ratio(after, masked)} | {_f(before)} | {_ratio(after_segment, before)} | "
            f"{r['loops_proposed']} | {r['loops_verified']} | {r['loops_accepted']} | "
            f"{r['false_loops_accepted']} | {r['loops_outside_gt_band']} | {r['segments']} | {r['fps']:.1f} |"
        )


def _f(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"


def _ratio(a: float | None, b: float | None) -> str:
    return "-" if a is None or not b else f"{a / b:.2f}"


def check_targets(rows: dict[str, dict[str, Any]]) -> list[str]:
    failures = []
    for name, r in rows.items():
        if r["false_loops_accepted"]:
            failures.append(f"{name}: {r['false_loops_accepted']} false loops accepted")
        if r["fps"] is not None and r["fps"] < 20:
            failures.append(f"{name}: {r['fps']:.1f} frames/s < 20")
        if name.startswith(CONTROL):
            if r["loops_accepted"]:
                failures.append(f"{name}: {r['loops_accepted']} loops accepted on the control")
        elif r["ate_rmse_after_all"] is None or r["ate_rmse_after_all"] > 0.5 * r["ate_rmse_masked_no_loops"]:
            failures.append(
                f"{name}: ATE after {r['ate_rmse_after_all']} > 0.5 x masked no-loops "
                f"{r['ate_rmse_masked_no_loops']}"
            )
    return failures


if __name__ == "__main__":
    sys.exit(main())
