"""A Sim(3) pose graph: drifting monocular odometry around a square, one loop closure, optimised.

A camera drives once around a 10 m x 10 m square, one keyframe per metre, and ends where it
started. Monocular odometry cannot observe scale, so its map scale drifts (here every step is
measured 1 % shorter than the one before, relative to the truth) and a small yaw bias bends the
path. The last keyframe recognises the first one (a loop closure: a relative Sim(3) that also sees
the scale ratio between the two keyframes), and the pose graph spreads the correction over the loop.

Everything goes through this project's backend, ``slam_backend.posegraph.GtsamPoseGraph``: poses
and measurements are homogeneous 4x4 matrices ``[s*R, t; 0, 1]``, covariances are 7x7 in gtsam's
Sim(3) tangent order (rotation, translation, log-scale). The default outlier rejection (PCM + GNC)
decides whether the loop is trusted.

Run: ``python examples/sim3_pose_graph_loop.py``
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence

import gtsam
import numpy as np

from slam_backend.posegraph import BackendConfig, GtsamPoseGraph

SIDE_M = 10  # side of the square (m); one keyframe per metre
SCALE_DRIFT = 0.99  # each odometry step is measured 1 % shorter (relative to the truth) than the last
YAW_BIAS_RAD = math.radians(0.3)  # per step
SEED = 7

# Odometry is good in rotation, poor in translation and blind to scale changes; the loop (from a
# geometric verification) sees everything, including the scale ratio.
ODOMETRY_COVARIANCE = np.diag([1e-5] * 3 + [4e-3] * 3 + [4e-4])
LOOP_COVARIANCE = np.diag([1e-5] * 3 + [1e-3] * 3 + [1e-5])


def pose(yaw: float, position: Sequence[float] | np.ndarray) -> np.ndarray:
    """A 4x4 rigid transform (a Sim(3) of scale 1): rotation about z by ``yaw``, then ``position``."""
    matrix = np.eye(4)
    matrix[:3, :3] = gtsam.Rot3.Rz(yaw).matrix()
    matrix[:3, 3] = position
    return matrix


def square_path() -> list[np.ndarray]:
    """True camera poses (metric, scale 1): one per metre around the square, back at the start."""
    poses = []
    position, heading = np.zeros(3), 0.0
    for k in range(4 * SIDE_M + 1):
        poses.append(pose(heading, position))
        position = position + np.array([math.cos(heading), math.sin(heading), 0.0])
        if (k + 1) % SIDE_M == 0:  # a corner: turn left
            heading += math.pi / 2
    return poses


def true_nodes(truth: list[np.ndarray]) -> list[np.ndarray]:
    """The poses a perfect monocular map would hold: true rotation and position, and the map scale
    of each keyframe (metres per map unit), which grows as the odometry's steps shrink."""
    nodes = []
    for k, matrix in enumerate(truth):
        node = matrix.copy()
        node[:3, :3] *= SCALE_DRIFT ** (-k)
        nodes.append(node)
    return nodes


def drifting_odometry(nodes: list[np.ndarray], rng: np.random.Generator) -> list[np.ndarray]:
    """Relative motions as a monocular VO reports them: steps in the previous keyframe's (drifting)
    map units, scale ratio 1 (VO cannot see its map scale change), a yaw bias and noise."""
    steps = [nodes[0]]  # the first keyframe's "odometry" is its world pose (anchored by a prior)
    for k in range(1, len(nodes)):
        exact = np.linalg.inv(nodes[k - 1]) @ nodes[k]
        yaw = math.atan2(exact[1, 0], exact[0, 0]) + YAW_BIAS_RAD + rng.normal(0.0, 0.002)
        translation = exact[:3, 3] + rng.normal(0.0, 0.01, 3) * [1, 1, 0]
        steps.append(pose(yaw, translation))
    return steps


def chain(steps: list[np.ndarray]) -> list[np.ndarray]:
    """Integrate the odometry (what the trajectory looks like without loop closure)."""
    poses = [steps[0]]
    for step in steps[1:]:
        poses.append(poses[-1] @ step)
    return poses


def position_errors(estimate: list[np.ndarray], truth: list[np.ndarray]) -> np.ndarray:
    """Distance (m) between estimated and true camera centres (both anchored at the first pose)."""
    return np.array([np.linalg.norm(e[:3, 3] - t[:3, 3]) for e, t in zip(estimate, truth, strict=True)])


def scale_of(matrix: np.ndarray) -> float:
    return float(np.cbrt(np.linalg.det(matrix[:3, :3])))


def main(argv: Sequence[str] | None = None) -> dict[str, float]:
    argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    ).parse_args(argv)
    rng = np.random.default_rng(SEED)
    truth = square_path()
    nodes = true_nodes(truth)
    steps = drifting_odometry(nodes, rng)
    last = len(truth) - 1

    # 1. Odometry only: add the keyframes one by one (iSAM2 under the hood).
    graph = GtsamPoseGraph(BackendConfig(mode="sim3"))  # default rejection: pcm+gnc
    for key, step in enumerate(steps):
        graph.add_keyframe(key, step, ODOMETRY_COVARIANCE)
    odometry = graph.estimate()
    before = [odometry[key] for key in range(len(steps))]
    assert np.allclose(before[last], chain(steps)[last], atol=1e-6)  # iSAM2 = integrated odometry

    # 2. The loop closure: the last keyframe sees the first. A geometric verifier measures the
    #    relative Sim(3) between the two keyframes' maps, including the scale ratio the odometry
    #    could not observe (here: the exact one; the verifier's noise would enter through
    #    LOOP_COVARIANCE).
    relative = np.linalg.inv(nodes[last]) @ nodes[0]
    decision = graph.add_loop(last, 0, relative, LOOP_COVARIANCE, {"detector": "example"})

    # 3. Optimise (estimate() runs the due GNC verification) and compare with the truth.
    optimised = graph.estimate()
    after = [optimised[key] for key in range(len(steps))]
    final = graph.decisions()[decision.loop_id]

    errors_before, errors_after = position_errors(before, truth), position_errors(after, truth)
    figures = {
        "end_drift_before_m": float(errors_before[last]),
        "end_drift_after_m": float(errors_after[last]),
        "ape_rmse_before_m": float(np.sqrt(np.mean(errors_before**2))),
        "ape_rmse_after_m": float(np.sqrt(np.mean(errors_after**2))),
        "scale_true": scale_of(nodes[last]),
        "scale_before": scale_of(before[last]),
        "scale_after": scale_of(after[last]),
    }
    print(f"Sim(3) pose graph: {len(steps)} keyframes around a {SIDE_M} m square, one loop {last} -> 0")
    print(f"loop decision: {final.status} ({final.reason})")
    print(
        f"end-point drift:       odometry {figures['end_drift_before_m']:.3f} m, "
        f"optimised {figures['end_drift_after_m']:.3f} m"
    )
    print(
        f"APE RMSE (positions):  odometry {figures['ape_rmse_before_m']:.3f} m, "
        f"optimised {figures['ape_rmse_after_m']:.3f} m"
    )
    print(
        f"map scale at the end:  true {figures['scale_true']:.3f}, odometry {figures['scale_before']:.3f}, "
        f"optimised {figures['scale_after']:.3f}"
    )
    return figures


if __name__ == "__main__":
    main()
