"""Benchmark of the pose-graph backend: outlier rejection quality and incremental cost.

* KITTI 00 mono-drift (``slam_backend.simulate``) with 0/10/30/50 % false loops, and the gtsam
  datasets sphere2500 (SE(3)) and city10000 (SE(2)) with 0/10/30 % random false loops, each with
  rejection none / huber / gnc / pcm / pcm+gnc: ATE RMSE (evo) and false loops accepted.
  The gtsam datasets are cut to their first ``--max-poses`` poses to keep the run short; sphere2500
  uses its generating noise (``SPHERE2500_SIGMAS``) since its file's information matrices are not it.
* Cost at 2 000 keyframes (KITTI 00, 30 % false loops, pcm+gnc): the median iSAM2 keyframe update
  around keyframe 2 000, and the median of ``HELD_OUT_LOOPS`` loop-closure events (held back while
  the graph is built, then added one by one) against one batch GNC pass (``rejection=gnc``) over the
  same graph, measured in the same run.

Usage: ``python -m eval.bench.backend [--quick] [--shared DIR] [--json OUT]``
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import time
from pathlib import Path
from typing import Any

import gtsam
import numpy as np

from frontends.cli_common import add_json_option, write_json
from frontends.trajectory_io import read_kitti_poses, read_times
from slam_backend.errors import PoseGraphError
from slam_backend.experiment import figures, run_problem
from slam_backend.graph_io import read_ground_truth, read_pose_graph
from slam_backend.posegraph import REJECTIONS, BackendConfig, GtsamPoseGraph
from slam_backend.problem import PoseGraphProblem
from slam_backend.simulate import MonoDriftConfig, add_false_loops, simulate_mono_drift

#: sphere2500's real edge noise (rotation, translation), measured against sphere2500_groundtruth.txt.
SPHERE2500_SIGMAS = (0.01, 0.01, 0.04, 0.1, 0.1, 0.1)
HELD_OUT_LOOPS = 5
#: Figures of a run whose optimisation failed (reported as such in the table).
FAILED: dict[str, Any] = {
    "ate_rmse_odometry": math.nan,
    "ate_rmse_optimized": math.nan,
    "false_accepted": -1,
    "true_rejected": -1,
    "optimize_seconds": math.nan,
}
TIMING_KEYFRAMES = 2000


def kitti_problem(shared: Path, ratio: float, seed: int) -> PoseGraphProblem:
    folder = shared / "data" / "trajectories"
    trajectory = read_kitti_poses(folder / "KITTI_00_gt.txt", read_times(folder / "KITTI_00_gt_times.txt"))
    return simulate_mono_drift(trajectory, MonoDriftConfig(seed=seed, outlier_ratio=ratio), "KITTI 00")


def gtsam_problem(name: str, ratio: float, seed: int, max_poses: int) -> PoseGraphProblem:
    graph, truth, sigmas = {
        "sphere2500": ("sphere2500.txt", "sphere2500_groundtruth.txt", SPHERE2500_SIGMAS),
        "city10000": ("T1_city10000_04.txt", "ISAM2_GT_city10000.txt", None),
    }[name]
    problem = read_pose_graph(gtsam.findExampleDataFile(graph), sigmas=sigmas)
    problem.gt_poses = read_ground_truth(gtsam.findExampleDataFile(truth), problem.keyframe_ids)
    problem = problem.truncated(max_poses)
    problem.name = name
    assert problem.gt_poses is not None
    extent = float(np.ptp(problem.gt_poses[:, :3, 3], axis=0).max())
    return add_false_loops(problem, ratio, np.random.default_rng(seed), min_distance=0.1 * extent)


def quality_rows(problem: PoseGraphProblem, ratio: float, max_checks: int) -> list[dict[str, Any]]:
    rows = []
    for rejection in REJECTIONS:
        config = BackendConfig(mode=problem.mode, rejection=rejection, pcm_max_checks=max_checks)
        row: dict[str, Any] = {"dataset": problem.name, "outliers": ratio, "rejection": rejection}
        try:
            rows.append(row | figures(problem, run_problem(problem, config)))
        except PoseGraphError as exc:  # a baseline without rejection can make the graph degenerate
            print(f"  {problem.name} {ratio:.0%} {rejection}: failed ({exc})", flush=True)
            rows.append(row | {"loops_true": problem.loops_true, "loops_false": problem.loops_false} | FAILED)
            continue
        print(f"  {problem.name} {ratio:.0%} {rejection}: {rows[-1]['ate_rmse_optimized']:.3f} m", flush=True)
    return rows


def timing(shared: Path, seed: int) -> dict[str, float]:
    """Keyframe and loop-event cost at 2 000 keyframes, and the batch GNC pass on the same graph."""
    problem = kitti_problem(shared, 0.3, seed).truncated(TIMING_KEYFRAMES)
    true_loops = [loop for loop in problem.loops if loop.is_true]
    held_out = true_loops[-HELD_OUT_LOOPS:]
    played = [loop for loop in problem.loops if all(loop is not h for h in held_out)]
    arrivals = dataclasses.replace(problem, loops=played).arrival_order()
    ours = GtsamPoseGraph(BackendConfig(rejection="pcm+gnc"))
    batch = GtsamPoseGraph(BackendConfig(rejection="gnc"))
    keyframe_seconds = []
    for position, key in enumerate(problem.keyframe_ids):
        step, covariance = problem.odometry[position], problem.odometry_covariances[position]
        tic = time.perf_counter()
        ours.add_keyframe(key, step, covariance)
        keyframe_seconds.append(time.perf_counter() - tic)
        batch.add_keyframe(key, step, covariance)
        for loop in arrivals[position]:
            ours.add_loop(loop.start, loop.end, loop.relative, loop.covariance)
            batch.add_loop(loop.start, loop.end, loop.relative, loop.covariance)
    event_seconds = []
    for loop in held_out:
        tic = time.perf_counter()
        ours.add_loop(loop.start, loop.end, loop.relative, loop.covariance)
        event_seconds.append(time.perf_counter() - tic)
        batch.add_loop(loop.start, loop.end, loop.relative, loop.covariance)
    tic = time.perf_counter()
    batch.resolve()
    gnc_seconds = time.perf_counter() - tic
    event = float(np.median(event_seconds))
    return {
        "keyframe_ms_median_at_2000": 1e3 * float(np.median(keyframe_seconds[-200:])),
        "loop_event_ms_median_at_2000": 1e3 * event,
        "batch_gnc_ms_at_2000": 1e3 * gnc_seconds,
        "batch_gnc_over_loop_event": gnc_seconds / event,
    }


def markdown(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| dataset | false loops | rejection | ATE odometry (m) | ATE optimised (m) | false accepted "
        "| true rejected | seconds |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row['dataset']} | {row['outliers']:.0%} ({row['loops_false']}/{row['loops_true']}) "
            f"| {row['rejection']} | {row['ate_rmse_odometry']:.3f} | {row['ate_rmse_optimized']:.3f} "
            f"| {row['false_accepted']} | {row['true_rejected']} | {row['optimize_seconds']:.1f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--shared", type=Path, default=Path(os.environ.get("SYMBIO_SHARED", "../shared")), help="shared data"
    )
    parser.add_argument("--quick", action="store_true", help="fewer ratios and smaller gtsam graphs")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--max-poses", type=int, help="poses kept of sphere2500 / city10000")
    add_json_option(parser)
    args = parser.parse_args(argv)
    max_poses = args.max_poses or (300 if args.quick else 600)
    kitti_ratios = (0.0, 0.3) if args.quick else (0.0, 0.1, 0.3, 0.5)
    gtsam_ratios = (0.0, 0.3) if args.quick else (0.0, 0.1, 0.3)
    started = time.perf_counter()
    cost = timing(args.shared, args.seed)
    rows: list[dict[str, Any]] = []
    for ratio in kitti_ratios:
        rows += quality_rows(kitti_problem(args.shared, ratio, args.seed), ratio, max_checks=200)
    for name in ("sphere2500", "city10000"):
        for ratio in gtsam_ratios:
            rows += quality_rows(gtsam_problem(name, ratio, args.seed, max_poses), ratio, max_checks=50)
    print(markdown(rows))
    print()
    print("| cost at 2000 keyframes | value |\n|---|---|")
    for key, value in cost.items():
        print(f"| {key} | {value:.1f} |")
    print(f"\ntotal {time.perf_counter() - started:.0f} s")
    flat: dict[str, Any] = dict(cost)
    for row in rows:
        prefix = f"{row['dataset'].replace(' ', '_')}_{round(100 * row['outliers'])}_{row['rejection']}"
        flat[f"{prefix}_ate"] = row["ate_rmse_optimized"]
        flat[f"{prefix}_false_accepted"] = row["false_accepted"]
    write_json(args.json, flat)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
