"""A realistic monocular (Sim(3)) pose-graph problem from a real ground-truth trajectory.

Noise model (``MonoDriftConfig``; defaults in brackets):

* Keyframes: a new one when the camera moved ``keyframe_distance`` [1 m] or turned
  ``keyframe_angle_deg`` [10 deg] since the last.
* Map scale: each keyframe ``k`` has a local map scale ``sigma_k`` (metres per map unit), a random
  walk in log space with standard deviation ``scale_drift_per_100m`` [1 %] after 100 m of travel
  (per keyframe: ``scale_drift_per_100m * sqrt(step / 100 m)``); ``sigma_0 = 1``.
* True keyframe node ``S_k = [sigma_k R_k, p_k; 0, 1]`` (GT pose relative to keyframe 0).
* Odometry ``k-1 -> k``: the true relative motion with the scale ratio set to 1 (monocular odometry
  cannot see its drift), perturbed on the right by ``Exp(e)``, ``e ~ N(0, C_odo)`` with rotation
  ``rotation_noise_deg`` [0.1 deg] and translation ``translation_noise`` [1 cm per m of step,
  in map units] per axis; ``C_odo``'s scale entry is the drift variance of that step, so the stated
  covariance is the true one.
* True loops: ``frontends.gt_loops.label_loop_pairs`` on the keyframes (``loop_max_distance`` [5 m],
  ``loop_max_angle_deg`` [30 deg], ``loop_min_time_gap`` [20 s]); per query keyframe the nearest
  reference, then one query every ``loop_stride`` [5] keyframes. Measurement ``S_i^-1 S_j`` (it sees
  the scale ratio, as Sim(3) alignment of two local maps does) perturbed by ``Exp(e)``,
  ``e ~ N(0, C_loop)`` (``loop_rotation_noise_deg`` [0.5 deg], ``loop_translation_noise`` [5 cm],
  ``loop_scale_noise`` [1 %]).
* False loops: ``round(R / (1 - R) * true)`` for ``outlier_ratio`` R, so R = false / (true + false).
  Each joins a random query keyframe to a random earlier keyframe at least ``false_loop_min_distance``
  [50 m] away (ground truth) and arrives with the query. Its transform is, alternately, the measured
  transform of a random true loop elsewhere or a small random transform drawn from ``C_loop`` scaled
  by ``false_loop_spread`` [20]; its covariance is ``C_loop`` like every true loop.

All randomness comes from ``np.random.default_rng(seed)``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from frontends.gt_loops import LoopLabelConfig, label_loop_pairs
from frontends.types import Trajectory
from slam_backend.lie import as_4x4, pose_group
from slam_backend.problem import LoopCandidate, PoseGraphProblem


@dataclass(frozen=True)
class MonoDriftConfig:
    seed: int = 1
    outlier_ratio: float = 0.0
    keyframe_distance: float = 1.0
    keyframe_angle_deg: float = 10.0
    scale_drift_per_100m: float = 0.01
    rotation_noise_deg: float = 0.1
    translation_noise: float = 0.01
    loop_max_distance: float = 5.0
    loop_max_angle_deg: float = 30.0
    loop_min_time_gap: float = 20.0
    loop_stride: int = 5
    loop_rotation_noise_deg: float = 0.5
    loop_translation_noise: float = 0.05
    loop_scale_noise: float = 0.01
    false_loop_min_distance: float = 50.0
    false_loop_spread: float = 20.0


def select_keyframes(poses: np.ndarray, distance: float, angle_deg: float) -> np.ndarray:
    """Indices of keyframes: a new one after moving ``distance`` or turning ``angle_deg``."""
    keep = [0]
    cos_limit = np.cos(np.radians(angle_deg))
    for index in range(1, len(poses)):
        last = poses[keep[-1]]
        moved = np.linalg.norm(poses[index, :3, 3] - last[:3, 3])
        cos_angle = (np.trace(last[:3, :3].T @ poses[index, :3, :3]) - 1.0) / 2.0
        if moved >= distance or cos_angle <= cos_limit:
            keep.append(index)
    return np.asarray(keep)


def _sim3(rotation: np.ndarray, position: np.ndarray, scale: float) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = scale * rotation
    matrix[:3, 3] = position
    return matrix


def simulate_mono_drift(trajectory: Trajectory, config: MonoDriftConfig, name: str = "") -> PoseGraphProblem:
    """Build the Sim(3) problem described in the module docstring from a GT trajectory."""
    rng = np.random.default_rng(config.seed)
    group = pose_group("sim3")
    all_poses = np.asarray(trajectory.poses_se3)
    chosen = select_keyframes(all_poses, config.keyframe_distance, config.keyframe_angle_deg)
    gt = np.linalg.inv(all_poses[chosen[0]]) @ all_poses[chosen]
    timestamps = np.asarray(trajectory.timestamps)[chosen]
    steps = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)
    drift_sigmas = config.scale_drift_per_100m * np.sqrt(steps / 100.0)
    log_scale = np.concatenate([[0.0], np.cumsum(rng.normal(0.0, drift_sigmas))])
    scales = np.exp(log_scale)
    nodes = [_sim3(pose[:3, :3], pose[:3, 3], s) for pose, s in zip(gt, scales, strict=True)]

    rot_var = np.radians(config.rotation_noise_deg) ** 2
    odometry = [np.eye(4)]
    covariances = [np.eye(7) * 1e-12]
    for k in range(1, len(nodes)):
        true_step = np.linalg.inv(nodes[k - 1]) @ nodes[k]
        true_step[:3, :3] /= np.cbrt(np.linalg.det(true_step[:3, :3]))  # odometry sees no scale change
        trans_var = (config.translation_noise * max(steps[k - 1], 0.1) / scales[k - 1]) ** 2
        covariance = np.diag([rot_var] * 3 + [trans_var] * 3 + [drift_sigmas[k - 1] ** 2 + 1e-12])
        spatial = covariance.copy()
        spatial[6, 6] = 0.0  # the scale error is the drift itself, already in the true step
        odometry.append(group.perturb(true_step, spatial, rng))
        covariances.append(covariance)

    loop_covariance = np.diag(
        [np.radians(config.loop_rotation_noise_deg) ** 2] * 3
        + [config.loop_translation_noise**2] * 3
        + [config.loop_scale_noise**2]
    )
    labels = LoopLabelConfig(
        max_distance=config.loop_max_distance,
        max_angle_deg=config.loop_max_angle_deg,
        min_time_gap=config.loop_min_time_gap,
    )
    pairs = label_loop_pairs(gt, timestamps, labels)
    true_loops: list[LoopCandidate] = []
    last_query = -config.loop_stride
    for query in np.unique(pairs[:, 0]) if len(pairs) else []:
        if query - last_query < config.loop_stride:
            continue
        refs = pairs[pairs[:, 0] == query, 1]
        ref = int(refs[np.argmin(np.linalg.norm(gt[refs, :3, 3] - gt[query, :3, 3], axis=1))])
        truth = np.linalg.inv(nodes[ref]) @ nodes[query]
        true_loops.append(
            LoopCandidate(ref, int(query), group.perturb(truth, loop_covariance, rng), loop_covariance, True)
        )
        last_query = int(query)

    problem = PoseGraphProblem(
        name=name or "mono-drift",
        mode="sim3",
        keyframe_ids=list(range(len(gt))),
        odometry=odometry,
        odometry_covariances=covariances,
        loops=true_loops,
        gt_poses=gt,
        timestamps=timestamps,
    )
    return add_false_loops(
        problem, config.outlier_ratio, rng, config.false_loop_min_distance, config.false_loop_spread
    )


def add_false_loops(
    problem: PoseGraphProblem,
    ratio: float,
    rng: np.random.Generator,
    min_distance: float,
    spread: float = 20.0,
) -> PoseGraphProblem:
    """Add ``round(R / (1 - R) * loops)`` false loops (R = ``ratio``) and sort loops by arrival.

    Each joins a random keyframe to a random earlier one more than ``min_distance`` away (ground
    truth when known, else dead reckoning); its transform is, alternately, that of a random true loop
    or a random transform drawn from a true loop's covariance times ``spread``; its covariance is that
    true loop's covariance.
    """
    if not 0.0 <= ratio < 1.0:
        raise ValueError(f"outlier ratio must be in [0, 1), got {ratio}")
    true_loops = [loop for loop in problem.loops if loop.is_true]
    group = pose_group(problem.mode)
    positions = (
        problem.gt_poses[:, :3, 3]
        if problem.gt_poses is not None
        else np.array([as_4x4(pose)[:3, 3] for pose in problem.dead_reckoning()])
    )
    wanted = round(ratio / (1.0 - ratio) * len(true_loops)) if true_loops else 0
    false_loops: list[LoopCandidate] = []
    attempts = 0
    while len(false_loops) < wanted and attempts < 100 * wanted:
        attempts += 1
        query = int(rng.integers(1, len(positions)))
        far = np.flatnonzero(np.linalg.norm(positions[:query] - positions[query], axis=1) > min_distance)
        if far.size == 0:
            continue
        ref = int(rng.choice(far))
        model = true_loops[int(rng.integers(len(true_loops)))]
        if len(false_loops) % 2 == 0:
            relative = model.relative
        else:
            relative = group.perturb(np.eye(group.matrix_size), model.covariance * spread**2, rng)
        ids = problem.keyframe_ids
        false_loops.append(LoopCandidate(ids[ref], ids[query], relative, model.covariance, False))
    position = {key: n for n, key in enumerate(problem.keyframe_ids)}
    loops = sorted(
        [*problem.loops, *false_loops], key=lambda loop: max(position[loop.start], position[loop.end])
    )
    return dataclasses.replace(problem, loops=loops)
