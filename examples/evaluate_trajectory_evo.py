"""Evaluate a monocular trajectory against ground truth with evo: APE after Sim(3) alignment, and RPE.

A monocular SLAM estimate lives in its own frame and at its own, unknown scale. Before comparing
it with ground truth it is aligned by Umeyama's method with scale (Sim(3)); evo does that
(``PoseTrajectory3D.align(reference, correct_scale=True)``) and returns the rotation, translation
and scale it found. Then:

* APE (absolute pose error, translation part): position error of every pose after alignment.
* RPE (relative pose error, translation part, over 10 frames): the local drift, independent of
  where the errors started.

Without arguments a ground-truth ellipse (30 s at 10 Hz) and a fake monocular estimate are made:
the ground truth's motion integrated with a slow scale random walk and a yaw bias, then expressed
in another frame at 0.4x the metric scale (so the scale to recover is 2.5). With two TUM files
(``timestamp tx ty tz qx qy qz qw``) they are read with ``frontends.trajectory_io.read_tum`` and
associated by timestamp (evo, 20 ms).

Run: ``python examples/evaluate_trajectory_evo.py [GROUNDTRUTH.txt ESTIMATE.txt]``
"""

from __future__ import annotations

import argparse
import copy
import math
from collections.abc import Sequence

import numpy as np
from evo.core import lie_algebra, metrics, sync
from evo.core.trajectory import PoseTrajectory3D

from frontends.trajectory_io import read_tum

MAP_SCALE = 0.4  # map units per metre of the fake estimate: the scale to recover is 1 / MAP_SCALE
SEED = 5


def yaw_pose(yaw: float, position: Sequence[float]) -> np.ndarray:
    return lie_algebra.se3(lie_algebra.so3_exp(np.array([0.0, 0.0, yaw])), np.asarray(position))


def ground_truth() -> PoseTrajectory3D:
    """A camera driving 30 s around a 6 x 4 m ellipse, heading along the path, bobbing 5 cm."""
    times = np.arange(300) / 10.0
    phase = 2 * math.pi * times / times[-1] * 1.05  # a bit more than one lap
    poses = []
    for t, a in zip(times, phase, strict=True):
        position = [3.0 * math.cos(a), 2.0 * math.sin(a), 1.4 + 0.05 * math.sin(3 * t)]
        heading = math.atan2(2.0 * math.cos(a), -3.0 * math.sin(a))
        poses.append(yaw_pose(heading, position))
    return PoseTrajectory3D(poses_se3=poses, timestamps=times)


def fake_monocular_estimate(reference: PoseTrajectory3D) -> PoseTrajectory3D:
    """The reference's motion re-integrated with scale and yaw drift, in another frame and scale."""
    rng = np.random.default_rng(SEED)
    gt = reference.poses_se3
    poses = [np.eye(4)]
    scale = 1.0
    for k in range(1, len(gt)):
        step = lie_algebra.relative_se3(gt[k - 1], gt[k])
        scale *= 1.0 + rng.normal(0.0, 0.001)  # monocular scale random walk
        drifted = yaw_pose(math.radians(0.01), [0, 0, 0]) @ step  # a small yaw bias per frame
        drifted[:3, 3] *= scale
        poses.append(poses[-1] @ drifted)
    # Express it in another world frame (the first camera's, rotated) at the map's scale.
    frame = yaw_pose(1.0, [0.5, -2.0, 0.3])
    for pose in poses:
        pose[:3, 3] *= MAP_SCALE
    return PoseTrajectory3D(
        poses_se3=[frame @ pose for pose in poses], timestamps=reference.timestamps.copy()
    )


def ape_rmse(reference: PoseTrajectory3D, estimate: PoseTrajectory3D) -> float:
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((reference, estimate))
    return float(ape.get_statistic(metrics.StatisticsType.rmse))


def rpe_rmse(reference: PoseTrajectory3D, estimate: PoseTrajectory3D, frames: int = 10) -> float:
    rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta=frames, all_pairs=True)
    rpe.process_data((reference, estimate))
    return float(rpe.get_statistic(metrics.StatisticsType.rmse))


def main(argv: Sequence[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("files", nargs="*", metavar="TUM_FILE", help="ground truth and estimate (TUM format)")
    files = parser.parse_args(argv).files
    if len(files) not in (0, 2):
        parser.error("give a ground-truth and an estimate file, or nothing for the synthetic example")
    if files:
        reference, estimate = sync.associate_trajectories(
            read_tum(files[0]), read_tum(files[1]), max_diff=0.02
        )
        true_scale = float("nan")
        print(f"{files[0]} vs {files[1]}: {reference.num_poses} associated poses")
    else:
        reference = ground_truth()
        estimate = fake_monocular_estimate(reference)
        true_scale = 1.0 / MAP_SCALE
        print(f"synthetic: {reference.num_poses} poses, {reference.path_length:.1f} m of ground truth")

    raw = ape_rmse(reference, estimate)  # no alignment: different frames, different scales

    se3 = copy.deepcopy(estimate)  # align() works in place
    se3.align(reference, correct_scale=False)  # rigid alignment only: wrong for monocular
    sim3 = copy.deepcopy(estimate)
    rotation, translation, scale = sim3.align(reference, correct_scale=True)  # Umeyama with scale

    figures = {
        "ape_rmse_unaligned_m": raw,
        "ape_rmse_se3_m": ape_rmse(reference, se3),
        "ape_rmse_sim3_m": ape_rmse(reference, sim3),
        "rpe_rmse_sim3_m": rpe_rmse(reference, sim3),
        "scale": float(scale),
        "true_scale": true_scale,
    }
    yaw = math.degrees(math.atan2(rotation[1, 0], rotation[0, 0]))
    print(f"APE RMSE unaligned:           {figures['ape_rmse_unaligned_m']:.3f} m")
    print(f"APE RMSE after SE(3) align:   {figures['ape_rmse_se3_m']:.3f} m (no scale: not for monocular)")
    print(f"APE RMSE after Sim(3) align:  {figures['ape_rmse_sim3_m']:.3f} m")
    print(f"RPE RMSE (10 frames), Sim(3): {figures['rpe_rmse_sim3_m']:.3f} m")
    print(f"Sim(3) alignment: scale {scale:.4f}, yaw {yaw:.1f} deg, translation {np.round(translation, 3)}")
    if not math.isnan(true_scale):
        print(f"true scale {true_scale:.4f}: recovered within {100 * abs(scale / true_scale - 1):.2f} %")
    return figures


if __name__ == "__main__":
    main()
