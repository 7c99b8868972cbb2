from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from frontends.errors import DatasetError
from frontends.gt_loops import LoopLabelConfig, label_loop_pairs, read_loop_pairs, write_loop_pairs
from frontends.trajectory_io import read_kitti_poses, read_times


def _poses_on_circle(n: int, laps: float, yaw_offset: float = 0.0) -> np.ndarray:
    """Cameras on a unit circle looking outwards (optical axis = camera z = radial direction)."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i, angle in enumerate(np.linspace(0, 2 * np.pi * laps, n, endpoint=False)):
        heading = angle + yaw_offset
        z_axis = np.array([np.cos(heading), np.sin(heading), 0.0])
        y_axis = np.array([0.0, 0.0, -1.0])
        poses[i, :3, :3] = np.column_stack([np.cross(y_axis, z_axis), y_axis, z_axis])
        poses[i, :3, 3] = [np.cos(angle), np.sin(angle), 0.0]
    return poses


def test_second_lap_revisits_first() -> None:
    n = 200
    poses = _poses_on_circle(n, laps=1.5)
    stamps = np.arange(n, dtype=float)
    pairs = label_loop_pairs(
        poses, stamps, LoopLabelConfig(max_distance=0.1, max_angle_deg=20, min_time_gap=50)
    )
    assert len(pairs) > 0
    assert (pairs[:, 0] > pairs[:, 1]).all()
    # frame q on lap 2 revisits q - n/1.5 (one lap = 133.3 frames)
    assert np.abs(pairs[:, 0] - pairs[:, 1] - n / 1.5).max() < 5


def test_no_pairs_within_time_gap_or_when_looking_away() -> None:
    n = 100
    stamps = np.arange(n, dtype=float)
    one_lap = _poses_on_circle(n, laps=0.9)
    assert len(label_loop_pairs(one_lap, stamps, LoopLabelConfig(max_distance=0.3, min_time_gap=5))) == 0
    hovering = _poses_on_circle(n, laps=0.02)  # never leaves: not a loop however long it lingers
    assert len(label_loop_pairs(hovering, stamps, LoopLabelConfig(max_distance=0.3, min_time_gap=5))) == 0
    out_and_back = np.concatenate([_poses_on_circle(50, 0.25), _poses_on_circle(50, 0.25, np.pi)[::-1]])
    pairs = label_loop_pairs(out_and_back, stamps, LoopLabelConfig(max_distance=0.2, min_time_gap=5))
    assert len(pairs) == 0  # same places, opposite viewing directions


def test_frames_without_pose_take_no_part() -> None:
    poses = _poses_on_circle(200, laps=1.5)
    poses[150:] = np.nan
    pairs = label_loop_pairs(poses, np.arange(200.0), LoopLabelConfig(max_distance=0.1, min_time_gap=50))
    assert len(pairs) > 0 and pairs.max() < 150


def test_pairs_file_round_trip_and_validation(tmp_path: Path) -> None:
    path = tmp_path / "gt_loop_pairs.txt"
    write_loop_pairs(path, np.array([[5, 1], [6, 2]]))
    np.testing.assert_array_equal(read_loop_pairs(path, 10), [[5, 1], [6, 2]])
    with pytest.raises(DatasetError, match=r"gt_loop_pairs\.txt:3: frame index out of range"):
        read_loop_pairs(path, 6)
    write_loop_pairs(path, np.zeros((0, 2), dtype=int))  # a scene without loops
    assert read_loop_pairs(path, 10).shape == (0, 2)
    path.write_text("5 1.5\n")
    with pytest.raises(DatasetError, match=r":1: frame indices must be integers"):
        read_loop_pairs(path)


@pytest.mark.shared
def test_kitti00_has_its_known_loops(shared: Path) -> None:
    data = shared / "data" / "trajectories"
    trajectory = read_kitti_poses(data / "KITTI_00_gt.txt", read_times(data / "KITTI_00_gt_times.txt"))
    pairs = label_loop_pairs(
        np.array(trajectory.poses_se3), trajectory.timestamps, LoopLabelConfig(max_distance=5.0)
    )
    queries = np.unique(pairs[:, 0])
    # KITTI 00 revisits along several stretches late in the drive (~760 query frames at 5 m).
    assert 600 < len(queries) < 1000
    assert queries.min() > 1500
