"""Covisibility ground truth of synthetic scenes: overlap from depth, and the labelling rules."""

from __future__ import annotations

import numpy as np
import pytest

from frontends.errors import ConfigError
from frontends.synth.covisibility import CovisibilityLabelConfig, label_covisible_pairs, overlap_matrix
from frontends.types import CameraIntrinsics

CAMERA = CameraIntrinsics(fx=100.0, fy=100.0, cx=63.5, cy=47.5, width=128, height=96)
CONFIG = CovisibilityLabelConfig(depth_step=8, sample_every=1)


def facing_wall(x: float, yaw_deg: float = 0.0, distance: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """A camera at (x, 0, 0) looking along +z (turned by ``yaw_deg`` about y) at the wall z = distance,
    and the inverse-depth grid it renders (0 where it sees no wall)."""
    yaw = np.radians(yaw_deg)
    rotation = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, [x, 0.0, 0.0]
    step = CONFIG.depth_step
    centres = step // 2
    u, v = np.meshgrid(
        np.arange(CAMERA.width // step) * step + centres, np.arange(CAMERA.height // step) * step + centres
    )
    rays = np.stack([(u - CAMERA.cx) / CAMERA.fx, (v - CAMERA.cy) / CAMERA.fy, np.ones(u.shape)], axis=-1)
    world_rays = rays @ rotation.T
    # Depth along the optical axis of the ray's hit on the plane z = distance.
    t = np.where(world_rays[..., 2] > 1e-9, distance / np.maximum(world_rays[..., 2], 1e-9), np.inf)
    inverse = np.where(np.isfinite(t), 1.0 / t, 0.0).astype(np.float32)
    return pose, inverse


def test_overlap_of_identical_shifted_and_opposite_views() -> None:
    views = [facing_wall(0.0), facing_wall(0.0), facing_wall(1.28), facing_wall(0.0, 180.0), facing_wall(5.0)]
    poses = np.stack([p for p, _ in views])
    grids = np.stack([g for _, g in views])
    overlap = overlap_matrix(grids, poses, CAMERA, CONFIG)
    assert overlap[0, 1] == overlap[1, 0] == 1.0
    # The wall seen at 2 m spans 2.56 m; moving 1.28 m sideways keeps half of it in view.
    assert abs(overlap[0, 2] - 0.5) < 0.08
    assert overlap[0, 3] == overlap[0, 4] == 0.0


def test_labels_need_overlap_time_gap_and_having_left() -> None:
    n = 6
    overlap = np.eye(n, dtype=np.float32)
    overlap[5, 0] = overlap[0, 5] = 0.8  # the camera comes back to frame 0's view
    overlap[1, 0] = overlap[0, 1] = 0.9  # the next frame of the same pass
    overlap[4, 2] = overlap[2, 4] = 0.2  # below min_overlap
    timestamps = np.arange(n) * 2.0
    poses = np.tile(np.eye(4), (n, 1, 1))
    config = CovisibilityLabelConfig(min_time_gap=3.0)
    assert label_covisible_pairs(overlap, poses, timestamps, config).tolist() == [[5, 0]]
    # The same wall seen from 4 m away is not a return to the place.
    far = poses.copy()
    far[5, 0, 3] = 4.0
    assert len(label_covisible_pairs(overlap, far, timestamps, config)) == 0
    # One-sided overlap (a close-up of part of a wide view) is not the same place.
    overlap[0, 5] = 0.1
    assert len(label_covisible_pairs(overlap, poses, timestamps, config)) == 0


def test_a_camera_that_never_looks_away_labels_no_loop() -> None:
    overlap = np.full((5, 5), 0.9, dtype=np.float32)
    timestamps = np.arange(5) * 10.0
    poses = np.tile(np.eye(4), (5, 1, 1))
    assert len(label_covisible_pairs(overlap, poses, timestamps, CovisibilityLabelConfig())) == 0


def test_a_passing_person_neither_hides_the_place_nor_counts_as_it() -> None:
    (pose, grid), (other_pose, other_grid) = facing_wall(0.0), facing_wall(0.0)
    person = np.zeros(grid.shape, bool)
    person[:, : grid.shape[1] // 2] = True
    occluded = np.where(person, np.float32(-1.0), other_grid)  # a person covers half of the second view
    overlap = overlap_matrix(np.stack([grid, occluded]), np.stack([pose, other_pose]), CAMERA, CONFIG)
    assert overlap[0, 1] == 1.0  # the wall behind the person counts as seen
    assert overlap[1, 0] == 1.0  # and the person's pixels are not sampled as part of the place
    # A wall in front of the first view's wall (depth 1 m instead of 2 m) does hide it.
    _, nearer = facing_wall(0.0, distance=1.0)
    blocked = overlap_matrix(np.stack([grid, nearer]), np.stack([pose, other_pose]), CAMERA, CONFIG)
    assert blocked[0, 1] == 0.0


def test_walking_away_along_a_wall_and_back_is_a_revisit() -> None:
    # The wall stays in view the whole time (overlap never below 10 %), but the camera went 3 m away.
    n = 6
    overlap = np.full((n, n), 0.5, dtype=np.float32)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = [0.0, 1.5, 3.0, 3.0, 1.5, 0.1]
    timestamps = np.arange(n) * 2.0
    pairs = label_covisible_pairs(overlap, poses, timestamps, CovisibilityLabelConfig(min_time_gap=3.0))
    assert [5, 0] in pairs.tolist()
    # Never farther than 2 m (2 x 1 m): hovering, no revisit.
    poses[:, 0, 3] = [0.0, 0.5, 1.0, 1.0, 0.5, 0.1]
    assert (
        len(label_covisible_pairs(overlap, poses, timestamps, CovisibilityLabelConfig(min_time_gap=3.0))) == 0
    )


def test_bad_label_settings_are_refused_by_name() -> None:
    with pytest.raises(ConfigError, match=r"loop_labels: depth_step must be >= 1"):
        CovisibilityLabelConfig(depth_step=0)
    with pytest.raises(ConfigError, match=r"min_overlap must be in \(0, 1\]"):
        CovisibilityLabelConfig(min_overlap=1.5)
