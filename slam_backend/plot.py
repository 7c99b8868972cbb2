"""Top-view plot of a run: ground truth, odometry, optimised, accepted and rejected loops (Agg)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from evo.core.trajectory import PoseTrajectory3D

from slam_backend.experiment import RunResult
from slam_backend.lie import as_4x4
from slam_backend.problem import PoseGraphProblem


def _aligned_xy(problem: PoseGraphProblem, poses: list[np.ndarray]) -> np.ndarray:
    matrices = [as_4x4(p) for p in poses]
    if problem.gt_poses is None:
        return np.array([m[:3, 3] for m in matrices])
    stamps = np.arange(len(matrices), dtype=np.float64)
    trajectory = PoseTrajectory3D(poses_se3=matrices, timestamps=stamps)
    trajectory.align(
        PoseTrajectory3D(poses_se3=list(problem.gt_poses), timestamps=stamps),
        correct_scale=problem.mode == "sim3",
    )
    return np.asarray(trajectory.positions_xyz)


def plot_run(path: str | Path, problem: PoseGraphProblem, result: RunResult) -> None:
    """Write a PNG; the two horizontal axes are the ones the ground truth spreads over most."""
    optimized = _aligned_xy(problem, result.estimate)
    odometry = _aligned_xy(problem, problem.dead_reckoning())
    reference = problem.gt_poses[:, :3, 3] if problem.gt_poses is not None else optimized
    axes = np.sort(np.argsort(np.ptp(reference, axis=0))[-2:])
    position = {key: n for n, key in enumerate(problem.keyframe_ids)}
    figure, ax = plt.subplots(figsize=(8, 8))
    if problem.gt_poses is not None:
        ax.plot(*reference[:, axes].T, color="black", lw=1.0, label="ground truth")
    ax.plot(*odometry[:, axes].T, color="tab:orange", lw=0.8, label="odometry")
    ax.plot(*optimized[:, axes].T, color="tab:blue", lw=1.0, label="optimised")
    for accepted, color, label in (
        (True, "tab:green", "accepted loops"),
        (False, "tab:red", "rejected loops"),
    ):
        segments = [
            optimized[[position[loop.start], position[loop.end]]][:, axes]
            for loop, decision in result.decisions
            if decision.accepted == accepted
        ]
        for n, segment in enumerate(segments):
            ax.plot(*segment.T, color=color, lw=0.6, alpha=0.7, label=label if n == 0 else None)
    ax.set_aspect("equal")
    ax.set_title(problem.name)
    ax.legend(loc="best")
    figure.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(figure)
