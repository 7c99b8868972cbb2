"""Ground-truth loops of a synthetic scene from what the cameras see, not only where they stand.

Two frames show the same place when they see the same surfaces. The renderer knows every frame's
depth, so the overlap of frames ``r`` and ``q`` is measured directly: the surface points behind a
regular grid of ``r``'s pixels, projected into ``q``, that land inside ``q``'s image in front of
whatever ``q`` sees there (depth within ``depth_tolerance``). Walking people are transient: their
pixels are not sampled, and a point hidden behind one counts as seen. The *mutual* overlap is the
smaller of the two directions, so a close-up of a detail inside a wide view is not the place.

``q`` revisits an earlier ``r`` when their mutual overlap is at least ``min_overlap``, the cameras
are within ``max_distance``, at least ``min_time_gap`` seconds passed, and the camera has been
away: some frame between them overlaps ``r`` by less than ``leave_overlap`` or is farther than
``leave_factor`` x ``max_distance`` from it (a camera hovering over one spot never labels its own pass).

Why not camera distance and angle alone (``frontends.gt_loops``, the labeller for real data): on
the room scenes (loop seeds 3 and 11, 900 frames) a quarter of the pairs within 0.6 m and 30 deg
share less than half of their view and some share none (looking past a corner or an object), while
views 0.7 m apart along the same wall share more than half (loop 11: frames 774 and 102, 54 %).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from frontends.errors import ConfigError
from frontends.types import CameraIntrinsics


@dataclass(frozen=True)
class CovisibilityLabelConfig:
    #: Smallest mutual overlap of a loop pair (share of each view's sampled surface points); 0.3 is
    #: OverlapNet's positive threshold for loop candidates (Chen et al., RSS 2020). Two 640x480
    #: views sharing 30 % still have hundreds of common ORB features for geometric verification.
    min_overlap: float = 0.3
    #: Largest distance of the two camera centres (m): views of one wall from 4 m apart overlap,
    #: but the second camera is not back at the first one's place. 1 m, ``LoopLabelConfig``'s
    #: indoor default.
    max_distance: float = 1.0
    #: The camera left ``r`` once a frame overlapped it by less than this, or moved farther than
    #: ``leave_factor`` x ``max_distance`` from it: walking along a wall to a turn and back never
    #: looks away from it (out-and-back: >= 32 % overlap all the way), yet the return is a revisit.
    leave_overlap: float = 0.1
    leave_factor: float = 2.0
    #: Minimum time between the two frames (s).
    min_time_gap: float = 3.0
    #: Pixel step of the stored inverse-depth grid (where a projected point is looked up: a coarse
    #: grid mistakes the depth of slanted floors and object edges), every how many of its cells a
    #: surface point is sampled, and the relative depth tolerance of a visible point.
    depth_step: int = 8
    sample_every: int = 4
    depth_tolerance: float = 0.1

    def __post_init__(self) -> None:
        failed = [
            f"{name} must be {rule}"
            for name, ok, rule in (
                ("min_overlap", 0 < self.min_overlap <= 1, "in (0, 1]"),
                ("leave_overlap", 0 <= self.leave_overlap < self.min_overlap, "in [0, min_overlap)"),
                ("max_distance", self.max_distance > 0, "> 0"),
                ("leave_factor", self.leave_factor > 0, "> 0"),
                ("min_time_gap", self.min_time_gap >= 0, ">= 0"),
                ("depth_step", self.depth_step >= 1, ">= 1"),
                ("sample_every", self.sample_every >= 1, ">= 1"),
                ("depth_tolerance", self.depth_tolerance > 0, "> 0"),
            )
            if not ok
        ]
        if failed:
            raise ConfigError(f"loop_labels: {'; '.join(failed)}")


def depth_grid(
    inverse_depth: np.ndarray,
    step: int,
    instances: np.ndarray | None = None,
    transient: np.ndarray | None = None,
) -> np.ndarray:
    """The inverse depth at the centres of ``step``-pixel cells (0 where nothing was drawn), -1 where
    the instance image shows one of the ``transient`` instances (something that hides the static
    scene only for a while)."""
    cells = (slice(step // 2, None, step), slice(step // 2, None, step))
    grid = np.array(inverse_depth[cells], dtype=np.float32)
    if instances is not None and transient is not None:
        grid[np.isin(instances[cells], transient)] = -1.0
    return grid


def overlap_matrix(
    grids: np.ndarray, poses: np.ndarray, camera: CameraIntrinsics, config: CovisibilityLabelConfig
) -> np.ndarray:
    """(N, N) share of frame r's sampled surface points that frame q sees (row r, column q).

    ``grids``: (N, gh, gw) inverse depths from ``depth_grid``; ``poses``: (N, 4, 4) camera-to-world.
    """
    count, rows, columns = grids.shape
    step, every = config.depth_step, config.sample_every
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
        seen = grids[frames, gy, gx]
        depth_error = np.abs(1.0 / np.maximum(seen, 1e-9) - z)
        # Behind a walking person the static scene is taken as seen: the place is the same.
        visible = inside & ((seen < 0) | ((seen > 0) & (depth_error <= config.depth_tolerance * z)))
        overlap[r] = visible.sum(axis=1) / world.shape[1]
    return overlap


def label_covisible_pairs(
    overlap: np.ndarray, poses: np.ndarray, timestamps: np.ndarray, config: CovisibilityLabelConfig
) -> np.ndarray:
    """All (query, reference) pairs with query > reference that revisit (see the module), sorted;
    ``poses`` (N, 4, 4) camera-to-world."""
    mutual = np.minimum(overlap, overlap.T)
    count = len(mutual)
    centres = poses[:, :3, 3]
    distance = np.linalg.norm(centres[:, None] - centres[None], axis=2)
    # First later frame that overlaps each frame by less than leave_overlap or is far from it.
    far = distance > config.leave_factor * config.max_distance
    away = np.triu((mutual < config.leave_overlap) | far, 1)
    left = np.where(away.any(axis=1), away.argmax(axis=1), count)
    query, ref = np.nonzero(np.tril(mutual >= config.min_overlap, -1))
    keep = (
        (timestamps[query] - timestamps[ref] >= config.min_time_gap)
        & (left[ref] < query)
        & (distance[query, ref] <= config.max_distance)
    )
    pairs = np.stack([query[keep], ref[keep]], axis=1).astype(np.int64)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
