"""The indexed covisibility labeller (``covisible_pairs``) against a brute-force reference: every
pair's overlap measured, every rule applied to the full matrices (the labeller before indexing)."""

from __future__ import annotations

import numpy as np
import pytest

from frontends.synth.covisibility import CovisibilityLabelConfig, covisible_pairs
from frontends.synth.trajectories import camera_path
from frontends.synth.world import SynthConfig


def brute_force_pairs(
    grids: np.ndarray, poses: np.ndarray, timestamps: np.ndarray, config: SynthConfig
) -> np.ndarray:
    """Every (N, N) overlap, then the revisit rules on dense matrices."""
    camera, labels = config.intrinsics, config.loop_labels
    count, rows, columns = grids.shape
    step, every = labels.depth_step, labels.sample_every
    u, v = np.meshgrid(np.arange(columns) * step + step // 2, np.arange(rows) * step + step // 2)
    sampled = (slice(every // 2, None, every), slice(every // 2, None, every))
    u, v = u[sampled], v[sampled]
    rays = np.stack([(u.ravel() - camera.cx) / camera.fx, (v.ravel() - camera.cy) / camera.fy])
    world_to_camera = np.linalg.inv(poses)
    frames = np.arange(count)[:, None]
    overlap = np.zeros((count, count), np.float32)
    for r in range(count):
        inverse = grids[r][sampled].ravel()
        drawn = inverse > 0
        if not drawn.any():
            continue
        in_r = np.vstack([rays[:, drawn] / inverse[drawn], 1.0 / inverse[drawn]])
        world = poses[r, :3, :3] @ in_r + poses[r, :3, 3:4]
        in_q = world_to_camera[:, :3, :3] @ world + world_to_camera[:, :3, 3:4]
        z = in_q[:, 2]
        front = z > 1e-6
        safe_z = np.where(front, z, 1.0)
        x = camera.fx * in_q[:, 0] / safe_z + camera.cx
        y = camera.fy * in_q[:, 1] / safe_z + camera.cy
        inside = front & (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
        gx = np.clip((x / step).astype(np.int64), 0, columns - 1)
        gy = np.clip((y / step).astype(np.int64), 0, rows - 1)
        seen = grids[frames, gy, gx]
        depth_error = np.abs(1.0 / np.maximum(seen, 1e-9) - z)
        visible = inside & ((seen < 0) | ((seen > 0) & (depth_error <= labels.depth_tolerance * z)))
        overlap[r] = visible.sum(axis=1) / world.shape[1]
    mutual = np.minimum(overlap, overlap.T)
    centres = poses[:, :3, 3]
    distance = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    # The first later frame that overlaps each frame by < leave_overlap or is far from it.
    away = np.triu(
        (mutual < labels.leave_overlap) | (distance > labels.leave_factor * labels.max_distance), 1
    )
    left = np.where(away.any(axis=1), away.argmax(axis=1), count)
    pairs = [
        (q, r)
        for q in range(count)
        for r in range(q)
        if mutual[q, r] >= labels.min_overlap
        and timestamps[q] - timestamps[r] >= labels.min_time_gap
        and distance[q, r] <= labels.max_distance
        and left[r] < q
    ]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


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
