"""``symbio posegraph``: optimise a pose-graph dataset or a simulated monocular problem and score it."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.config import load_config
from frontends.errors import ConfigError
from frontends.trajectory_io import (
    TRAJECTORY_FORMATS,
    read_kitti_poses,
    read_times,
    read_tum,
    write_trajectory,
)
from frontends.types import Trajectory
from slam_backend.experiment import figures, run_problem
from slam_backend.graph_io import GRAPH_FORMATS, read_ground_truth, read_pose_graph
from slam_backend.lie import as_4x4
from slam_backend.posegraph import REJECTIONS, BackendConfig
from slam_backend.problem import PoseGraphProblem
from slam_backend.simulate import MonoDriftConfig, add_false_loops, simulate_mono_drift


def add_parser(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "posegraph",
        help="optimise a pose graph (g2o/TORO dataset or simulated monocular drift) with loop outliers",
        description="Optimise a pose-graph dataset (--g2o) or a monocular Sim(3) problem simulated from a "
        "ground-truth trajectory (--trajectory --simulate mono-drift), optionally with a ratio of false "
        "loops, and report ATE (evo APE) and the outlier-rejection counts.",
    )
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--g2o", type=Path, metavar="FILE", help="pose-graph file (g2o, TORO, city10000)")
    source.add_argument(
        "--trajectory", type=Path, metavar="GT", help="ground-truth trajectory to simulate from"
    )
    parser.add_argument(
        "--sigmas",
        type=_sigmas,
        help="comma-separated sigmas replacing every --g2o edge's noise model (group tangent order)",
    )
    parser.add_argument("--graph-format", choices=GRAPH_FORMATS, default="auto", help="format of --g2o")
    parser.add_argument(
        "--gt", type=Path, help="ground truth for --g2o (graph file, x y theta table, TUM, KITTI)"
    )
    parser.add_argument("--format", dest="fmt", choices=TRAJECTORY_FORMATS, help="format of --trajectory")
    parser.add_argument(
        "--times", type=Path, help="KITTI times file (default: <GT stem>_times.txt if present)"
    )
    parser.add_argument(
        "--simulate", choices=["mono-drift"], default="mono-drift", help="problem to simulate"
    )
    parser.add_argument(
        "--outliers", type=float, default=0.0, metavar="R", help="false / (true + false) loops"
    )
    parser.add_argument("--seed", type=int, default=1, help="seed of the simulation and the false loops")
    parser.add_argument("--rejection", choices=REJECTIONS, help="loop outlier rejection (overrides config)")
    parser.add_argument("--config", type=Path, help="YAML of BackendConfig keys")
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="BackendConfig key"
    )
    parser.add_argument(
        "--sim-set",
        dest="sim_overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="MonoDriftConfig key (noise model of --simulate)",
    )
    parser.add_argument("--plot", type=Path, metavar="PNG", help="plot GT / odometry / optimised and loops")
    parser.add_argument("--save", type=Path, metavar="JSON", help="save the pose graph (GtsamPoseGraph.load)")
    parser.add_argument("--output", type=Path, metavar="FILE", help="write the optimised trajectory")
    parser.add_argument(
        "--output-format", choices=TRAJECTORY_FORMATS, default="tum", help="format of --output"
    )
    add_json_option(parser)
    parser.set_defaults(handler=run)


def _sigmas(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(v) for v in text.split(","))
    except ValueError:
        shown = text if len(text) <= 60 else text[:60] + "..."
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {shown!r}") from None


def _read_trajectory(path: Path, fmt: str | None, times: Path | None) -> Trajectory:
    if fmt is None:
        raise ConfigError("--trajectory needs --format kitti|tum")
    if fmt == "tum":
        return read_tum(path)
    beside = path.with_name(f"{path.stem}_times.txt")
    stamps_file = times or (beside if beside.is_file() else None)
    return read_kitti_poses(path, read_times(stamps_file) if stamps_file else None)


def build_problem(args: argparse.Namespace) -> PoseGraphProblem:
    if not 0.0 <= args.outliers < 1.0:
        raise ConfigError(f"--outliers must be in [0, 1), got {args.outliers}")
    if args.trajectory is not None:
        sim_config = load_config(
            MonoDriftConfig,
            None,
            [*args.sim_overrides, f"seed={args.seed}", f"outlier_ratio={args.outliers}"],
        )
        trajectory = _read_trajectory(args.trajectory, args.fmt, args.times)
        return simulate_mono_drift(trajectory, sim_config, name=f"{args.trajectory.name} mono-drift")
    problem = read_pose_graph(args.g2o, args.graph_format, args.sigmas)
    if args.gt is not None:
        problem.gt_poses = read_ground_truth(args.gt, problem.keyframe_ids)
    if args.outliers > 0:
        extent = np.ptp(
            problem.gt_poses[:, :3, 3] if problem.gt_poses is not None else np.zeros((1, 3)), axis=0
        )
        problem = add_false_loops(
            problem, args.outliers, np.random.default_rng(args.seed), min_distance=0.1 * float(extent.max())
        )
    return problem


def run(args: argparse.Namespace) -> int:
    problem = build_problem(args)
    overrides = [*args.overrides, f"mode={problem.mode}"]
    if args.rejection:
        overrides.append(f"rejection={args.rejection}")
    config = load_config(BackendConfig, args.config, overrides)
    result = run_problem(problem, config)
    measured = figures(problem, result)
    print(f"{problem.name}: {len(problem.keyframe_ids)} poses, rejection {config.rejection}")
    print_figures(measured)
    write_json(args.json, measured)
    if args.plot:
        from slam_backend.plot import plot_run

        plot_run(args.plot, problem, result)
    if args.save:
        result.backend.save(args.save)
    if args.output:
        stamps = problem.timestamps if problem.timestamps is not None else np.arange(len(result.estimate))
        trajectory = Trajectory(poses_se3=[as_4x4(p) for p in result.estimate], timestamps=np.asarray(stamps))
        write_trajectory(args.output, trajectory, args.output_format)
    return 0
