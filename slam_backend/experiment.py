"""Feed a :class:`PoseGraphProblem` to a backend the way a SLAM frontend would, and score it.

Keyframes arrive in order; each loop arrives with the later of its two keyframes. ATE is evo's APE
(translation part, RMSE) after evo's Umeyama alignment: Sim(3) (``correct_scale``) for ``sim3``
problems, SE(3) otherwise.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from evo.core import metrics
from evo.core.trajectory import PoseTrajectory3D

from slam_backend.lie import as_4x4
from slam_backend.posegraph import BackendConfig, GtsamPoseGraph, LoopDecision
from slam_backend.problem import LoopCandidate, PoseGraphProblem


@dataclass
class RunResult:
    backend: GtsamPoseGraph
    estimate: list[np.ndarray]
    decisions: list[tuple[LoopCandidate, LoopDecision]]
    keyframe_seconds: list[float] = field(default_factory=list)
    #: Seconds of each loop event (all loops that arrive with one keyframe), with its keyframe count.
    loop_event_seconds: list[tuple[int, float]] = field(default_factory=list)
    optimize_seconds: float = 0.0


def run_problem(problem: PoseGraphProblem, config: BackendConfig) -> RunResult:
    """Build the graph incrementally; ``optimize_seconds`` covers everything but ATE."""
    backend = GtsamPoseGraph(config)
    arrivals = problem.arrival_order()
    submitted: list[tuple[LoopCandidate, int]] = []
    keyframe_seconds: list[float] = []
    loop_seconds: list[tuple[int, float]] = []
    started = time.perf_counter()
    for position, key in enumerate(problem.keyframe_ids):
        tic = time.perf_counter()
        backend.add_keyframe(key, problem.odometry[position], problem.odometry_covariances[position])
        keyframe_seconds.append(time.perf_counter() - tic)
        if arrivals[position]:
            tic = time.perf_counter()
            decided = backend.add_loops(
                [(loop.start, loop.end, loop.relative, loop.covariance, None) for loop in arrivals[position]]
            )
            submitted.extend((loop, d.loop_id) for loop, d in zip(arrivals[position], decided, strict=True))
            loop_seconds.append((position + 1, time.perf_counter() - tic))
    poses = backend.estimate()
    optimize_seconds = time.perf_counter() - started
    final = backend.decisions()
    return RunResult(
        backend=backend,
        estimate=[poses[key] for key in problem.keyframe_ids],
        decisions=[(loop, final[loop_id]) for loop, loop_id in submitted],
        keyframe_seconds=keyframe_seconds,
        loop_event_seconds=loop_seconds,
        optimize_seconds=optimize_seconds,
    )


def ate_rmse(
    gt_poses: np.ndarray, poses: list[np.ndarray], timestamps: np.ndarray, with_scale: bool
) -> float:
    """evo APE (translation, RMSE) of ``poses`` against ``gt_poses`` after Umeyama alignment."""
    reference = PoseTrajectory3D(poses_se3=list(gt_poses), timestamps=timestamps)
    estimated = PoseTrajectory3D(poses_se3=[as_4x4(p) for p in poses], timestamps=timestamps)
    estimated.align(reference, correct_scale=with_scale)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((reference, estimated))
    return float(ape.get_statistic(metrics.StatisticsType.rmse))


def figures(problem: PoseGraphProblem, result: RunResult) -> dict[str, float | int | None]:
    """The flat figures of ``symbio posegraph --json``."""
    false_accepted = sum(1 for loop, d in result.decisions if not loop.is_true and d.accepted)
    true_rejected = sum(1 for loop, d in result.decisions if loop.is_true and not d.accepted)
    ate_odometry: float | None = None
    ate_optimized: float | None = None
    if problem.gt_poses is not None:
        stamps = (
            problem.timestamps
            if problem.timestamps is not None
            else np.arange(len(problem.keyframe_ids), dtype=np.float64)
        )
        with_scale = problem.mode == "sim3"
        ate_odometry = ate_rmse(problem.gt_poses, problem.dead_reckoning(), stamps, with_scale)
        ate_optimized = ate_rmse(problem.gt_poses, result.estimate, stamps, with_scale)
    return {
        "ate_rmse_odometry": ate_odometry,
        "ate_rmse_optimized": ate_optimized,
        "loops_true": problem.loops_true,
        "loops_false": problem.loops_false,
        "false_accepted": false_accepted,
        "true_rejected": true_rejected,
        "optimize_seconds": result.optimize_seconds,
        "poses": len(problem.keyframe_ids),
    }
