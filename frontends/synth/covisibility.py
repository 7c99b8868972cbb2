"""Ground-truth loops of a synthetic scene from what the cameras see, not only where they stand.

Two frames show the same place when they see the same surfaces. The renderer knows every frame's
depth, so the overlap of frames ``r`` and ``q`` is measured directly: the surface points behind a
regular grid of ``r``'s pixels, projected into ``q``, that land inside ``q``'s image in front of
whatever ``q`` sees there (depth within ``depth_tolerance``); the *mutual* overlap is the smaller
of the two directions, so a close-up of a detail inside a wide view does not count as the place.

``q`` revisits an earlier ``r`` when their mutual overlap is at least ``min_overlap``, at least
``min_time_gap`` seconds passed, and the camera has been away: some frame between them overlaps
``r`` by less than ``leave_overlap`` (a camera hovering over one spot never labels its own pass).

Why not camera distance and angle alone (``frontends.gt_loops``): on the room scenes a camera
0.7 m and 6 deg from an earlier pose saw 55-77 % of the same wall but fell outside a 0.6 m band,
while poses inside the band looking past a corner shared as little as 2 % of their view. Measured
on loop seeds 3 and 11 (900 frames): 5 % of the distance band's pairs overlapped by less than 0.26.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from frontends.types import CameraIntrinsics


@dataclass(frozen=True)
class CovisibilityLabelConfig:
    #: Smallest mutual overlap of a loop pair (share of each view's sampled surface points).
    min_overlap: float = 0.5
    #: The camera left ``r`` once a frame overlapped it by less than this.
    leave_overlap: float = 0.1
    #: Minimum time between the two frames (s).
    min_time_gap: float = 3.0
    #: Pixel step of the sampling grid and the relative depth tolerance of a visible point.
    grid_step: int = 32
    depth_tolerance: float = 0.1


def depth_grid(inverse_depth: np.ndarray, step: int) -> np.ndarray:
    """The inverse depth at the centres of ``step``-pixel cells (0 where nothing was drawn)."""
    return np.ascontiguousarray(inverse_depth[step // 2 :: step, step // 2 :: step], dtype=np.float32)


def overlap_matrix(
    grids: np.ndarray, poses: np.ndarray, camera: CameraIntrinsics, config: CovisibilityLabelConfig
) -> np.ndarray:
    """(N, N) share of frame r's sampled surface points that frame q sees (row r, column q).

    ``grids``: (N, gh, gw) inverse depths from ``depth_grid``; ``poses``: (N, 4, 4) camera-to-world.
    """
    count, rows, columns = grids.shape
    step = config.grid_step
    u, v = np.meshgrid(np.arange(columns) * step + step // 2, np.arange(rows) * step + step // 2)
    rays = np.stack([(u.ravel() - camera.cx) / camera.fx, (v.ravel() - camera.cy) / camera.fy])
    world_to_camera = np.linalg.inv(poses)
    overlap = np.zeros((count, count), np.float32)
    for r in range(count):
        inverse = grids[r].ravel()
        drawn = inverse > 0
        if not drawn.any():
            continue
        in_r = np.vstack([rays[:, drawn] / inverse[drawn], 1.0 / inverse[drawn]])
        world = poses[r, :3, :3] @ in_r + poses[r, :3, 3:4]
        # Every frame at once: (N, 3, P) points in each camera.
        in_q = world_to_camera[:, :3, :3] @ world + world_to_camera[:, :3, 3:4]
        z = in_q[:, 2]
        front = z > 1e-6
        safe_z = np.where(front, z, 1.0)
        x = camera.fx * in_q[:, 0] / safe_z + camera.cx
        y = camera.fy * in_q[:, 1] / safe_z + camera.cy
        inside = front & (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
        gx = np.clip((x / step).astype(np.int64), 0, columns - 1)
        gy = np.clip((y / step).astype(np.int64), 0, rows - 1)
        seen = grids[np.arange(count)[:, None], gy, gx]
        depth_error = np.abs(1.0 / np.maximum(seen, 1e-9) - z)
        visible = inside & (seen > 0) & (depth_error <= config.depth_tolerance * z)
        overlap[r] = visible.sum(axis=1) / world.shape[1]
    return overlap


def label_covisible_pairs(
    overlap: np.ndarray, timestamps: np.ndarray, config: CovisibilityLabelConfig
) -> np.ndarray:
    """All (query, reference) pairs with query > reference that revisit (see the module), sorted."""
    mutual = np.minimum(overlap, overlap.T)
    count = len(mutual)
    # First later frame that overlaps each frame by less than leave_overlap (count if none).
    away = np.triu(mutual < config.leave_overlap, 1)
    left = np.where(away.any(axis=1), away.argmax(axis=1), count)
    query, ref = np.nonzero(np.tril(mutual >= config.min_overlap, -1))
    keep = (timestamps[query] - timestamps[ref] >= config.min_time_gap) & (left[ref] < query)
    pairs = np.stack([query[keep], ref[keep]], axis=1).astype(np.int64)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
