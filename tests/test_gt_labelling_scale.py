"""The indexed covisibility labeller (``covisible_pairs``) against the dense one: every pair's
overlap measured, every rule applied to the full matrices."""

from __future__ import annotations

import numpy as np
import pytest

from frontends.synth.covisibility import (
    CovisibilityLabelConfig,
    covisible_pairs,
    label_covisible_pairs,
    overlap_matrix,
)
from frontends.synth.trajectories import camera_path
from frontends.synth.world import SynthConfig


def brute_force_pairs(
    grids: np.ndarray, poses: np.ndarray, timestamps: np.ndarray, config: SynthConfig
) -> np.ndarray:
    """Every (N, N) overlap, then the revisit rules on the dense matrices (the labeller before
    indexing; ``tests/test_covisibility.py`` checks both against analytic cases)."""
    overlap = overlap_matrix(grids, poses, config.intrinsics, config.loop_labels)
    return label_covisible_pairs(overlap, poses, timestamps, config.loop_labels)


def room_depth(config: SynthConfig, poses: np.ndarray, seed: int) -> np.ndarray:
    """Inverse-depth grids of the empty room (a box) plus a few boxes along the walls, with a
    passing person (-1) now and then; analytic, so no rendering is needed."""
    camera, step = config.intrinsics, config.loop_labels.depth_step
    rng = np.random.default_rng(seed)
    sx, sy, sz = config.room_size
    boxes = [(np.array([-sx / 2, -sy / 2, 0.0]), np.array([sx / 2, sy / 2, sz]), True)]
    for _ in range(6):
        size = rng.uniform([0.4, 0.4, 0.5], [1.2, 1.0, 2.0])
        cx = rng.uniform(-0.4, 0.4) * sx
        cy = (sy / 2 - size[1] / 2 - 0.05) * rng.choice([-1.0, 1.0])
        low = np.array([cx - size[0] / 2, cy - size[1] / 2, 0.0])
        boxes.append((low, low + size, False))
    u, v = np.meshgrid(
        np.arange(camera.width // step) * step + step // 2,
        np.arange(camera.height // step) * step + step // 2,
    )
    rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(u.shape)], -1).reshape(
        -1, 3
    )
    grids = np.zeros((len(poses), *u.shape), np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        for i, pose in enumerate(poses):
            direction, origin = rays @ pose[:3, :3].T, pose[:3, 3]
            depth = np.full(len(rays), np.inf)
            for low, high, inside in boxes:
                t_low, t_high = (low - origin) / direction, (high - origin) / direction
                if inside:
                    exit_ = np.nanmin(
                        np.where(np.maximum(t_low, t_high) > 0, np.maximum(t_low, t_high), np.inf), 1
                    )
                    depth = np.minimum(depth, exit_)
                else:
                    near = np.nanmax(np.minimum(t_low, t_high), axis=1)
                    far = np.nanmin(np.maximum(t_low, t_high), axis=1)
                    depth = np.where((near <= far) & (near > 0.05) & (near < depth), near, depth)
            grids[i] = np.where(np.isfinite(depth), 1.0 / depth, 0.0).reshape(u.shape)
            if i % 40 < 8:
                grids[i, 15:45, 10 * (i % 40) : 10 * (i % 40) + 15] = -1.0
    return grids


@pytest.mark.parametrize(("trajectory", "seed"), [("loop", 1), ("out-and-back", 3), ("figure8", 2)])
def test_indexed_labelling_equals_brute_force(trajectory: str, seed: int) -> None:
    # Few frames at a low frame rate: ~300 frames still cover the whole path, so there are revisits,
    # frames that hover, and pairs rejected by each rule.
    config = SynthConfig(trajectory=trajectory, frames=300, fps=10.0, seed=seed)
    path = camera_path(config)
    grids = room_depth(config, path.poses, seed)
    expected = brute_force_pairs(grids, path.poses, path.timestamps, config)
    pairs = covisible_pairs(grids, path.poses, path.timestamps, config.intrinsics, config.loop_labels)
    assert len(expected) > 50  # the comparison is not vacuous
    assert pairs.dtype == expected.dtype and pairs.shape == expected.shape
    assert np.array_equal(pairs, expected)


def test_indexed_labelling_applies_every_rule() -> None:
    """Looser and stricter configs change the pairs the same way in both labellers."""
    base = SynthConfig(trajectory="out-and-back", frames=240, fps=8.0, seed=5)
    path = camera_path(base)
    grids = room_depth(base, path.poses, 5)
    for labels in (
        CovisibilityLabelConfig(max_distance=0.5, leave_factor=3.0),
        CovisibilityLabelConfig(min_overlap=0.6, leave_overlap=0.4, min_time_gap=1.0),
        CovisibilityLabelConfig(max_distance=2.0, leave_factor=0.5, sample_every=2),
    ):
        config = SynthConfig(trajectory="out-and-back", frames=240, fps=8.0, seed=5, loop_labels=labels)
        expected = brute_force_pairs(grids, path.poses, path.timestamps, config)
        pairs = covisible_pairs(grids, path.poses, path.timestamps, config.intrinsics, labels)
        assert np.array_equal(pairs, expected)
