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
from scipy.spatial import cKDTree

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


class _Projector:
    """The overlap of one frame's sampled surface points with any chosen frames (``overlap_matrix``'s
    arithmetic, evaluated for a subset of the columns)."""

    def __init__(
        self, grids: np.ndarray, poses: np.ndarray, camera: CameraIntrinsics, config: CovisibilityLabelConfig
    ) -> None:
        self.grids, self.poses, self.camera, self.config = grids, poses, camera, config
        _, rows, columns = grids.shape
        step, every = config.depth_step, config.sample_every
        u, v = np.meshgrid(np.arange(columns) * step + step // 2, np.arange(rows) * step + step // 2)
        self.sampled = (slice(every // 2, None, every), slice(every // 2, None, every))
        u, v = u[self.sampled], v[self.sampled]
        self.rays = np.stack([(u.ravel() - camera.cx) / camera.fx, (v.ravel() - camera.cy) / camera.fy])
        self.world_to_camera = np.linalg.inv(poses)

    def overlaps(self, r: int, targets: np.ndarray) -> np.ndarray:
        """Share of frame ``r``'s sampled surface points that each of the ``targets`` frames sees."""
        counts, total = self._visible(r, targets, 1)
        if total == 0:
            return np.zeros(len(targets), np.float32)
        return (counts / total).astype(np.float32)

    def at_least(self, r: int, targets: np.ndarray, threshold: float, every: int) -> np.ndarray:
        """``overlaps(r, targets) >= threshold``, first decided on every ``every``-th point alone.

        Exact: the full count lies between the count on those points and that count plus the points
        left out, and count -> float32(count / total) is monotone, so a bound on the right side of
        the threshold decides; only the undecided targets are measured on all points."""
        counts, total = self._visible(r, targets, every)
        if total == 0:
            return np.zeros(len(targets), np.float32) >= threshold
        left_out = total - len(range(0, total, every))
        sure = (counts / total).astype(np.float32) >= threshold
        possible = ((counts + left_out) / total).astype(np.float32) >= threshold
        undecided = possible & ~sure
        if undecided.any():
            sure[undecided] = self.overlaps(r, targets[undecided]) >= threshold
        return sure

    def _visible(self, r: int, targets: np.ndarray, every: int) -> tuple[np.ndarray, int]:
        """How many of frame ``r``'s sampled surface points (every ``every``-th of them) each target
        sees, and how many points ``r`` has in all."""
        camera, config, grids = self.camera, self.config, self.grids
        _, rows, columns = grids.shape
        step = config.depth_step
        inverse = grids[r][self.sampled].ravel()
        drawn = inverse > 0
        if not drawn.any() or len(targets) == 0:
            return np.zeros(len(targets), np.int64), int(drawn.sum())
        in_r = np.vstack([self.rays[:, drawn] / inverse[drawn], 1.0 / inverse[drawn]])
        world = self.poses[r, :3, :3] @ in_r + self.poses[r, :3, 3:4]
        # All targets at once: (T, 3, P) points in each camera (all points: the same matrix product
        # as overlap_matrix's, bit for bit, before any are left out).
        world_to_camera = self.world_to_camera[targets]
        in_q = (world_to_camera[:, :3, :3] @ world + world_to_camera[:, :3, 3:4])[:, :, ::every]
        z = in_q[:, 2]
        front = z > 1e-6
        safe_z = np.where(front, z, 1.0)
        x = camera.fx * in_q[:, 0] / safe_z + camera.cx
        y = camera.fy * in_q[:, 1] / safe_z + camera.cy
        inside = front & (x >= 0) & (x < camera.width) & (y >= 0) & (y < camera.height)
        # The depth test only for the points inside the image (the same arithmetic, fewer elements).
        which, point = np.nonzero(inside)
        x, y, z = x[which, point], y[which, point], z[which, point]
        gx = np.clip((x / step).astype(np.int64), 0, columns - 1)
        gy = np.clip((y / step).astype(np.int64), 0, rows - 1)
        seen = grids[targets[which], gy, gx]
        depth_error = np.abs(1.0 / np.maximum(seen, 1e-9) - z)
        # Behind a walking person the static scene is taken as seen: the place is the same.
        visible = (seen < 0) | ((seen > 0) & (depth_error <= config.depth_tolerance * z))
        return np.bincount(which[visible], minlength=len(targets)), world.shape[1]

    def pair_at_least(
        self, sources: np.ndarray, targets: np.ndarray, threshold: float, every: int
    ) -> np.ndarray:
        """``overlap[sources[k], targets[k]] >= threshold`` for each k (one batch per source frame)."""
        result = np.zeros(len(sources), bool)
        if len(sources) == 0:
            return result
        order = np.argsort(sources, kind="stable")
        frames, starts = np.unique(sources[order], return_index=True)
        for frame, block in zip(frames, np.split(order, starts[1:]), strict=True):
            result[block] = self.at_least(int(frame), targets[block], threshold, every)
        return result


def overlap_matrix(
    grids: np.ndarray, poses: np.ndarray, camera: CameraIntrinsics, config: CovisibilityLabelConfig
) -> np.ndarray:
    """(N, N) share of frame r's sampled surface points that frame q sees (row r, column q).

    ``grids``: (N, gh, gw) inverse depths from ``depth_grid``; ``poses``: (N, 4, 4) camera-to-world.
    """
    projector = _Projector(grids, poses, camera, config)
    count = len(grids)
    every = np.arange(count)
    overlap = np.zeros((count, count), np.float32)
    for r in range(count):
        overlap[r] = projector.overlaps(r, every)
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


def covisible_pairs(
    grids: np.ndarray,
    poses: np.ndarray,
    timestamps: np.ndarray,
    camera: CameraIntrinsics,
    config: CovisibilityLabelConfig,
) -> np.ndarray:
    """``label_covisible_pairs(overlap_matrix(grids, poses, camera, config), poses, timestamps, config)``,
    the same pairs in the same order, without the (N, N) overlap matrix: only the overlaps that can
    decide a pair are measured.

    Candidates come from a k-d tree over the camera centres (pairs within ``max_distance``); their
    mutual overlap is measured one direction at a time; "the camera has been away" is decided by the
    first later frame farther than ``leave_factor`` x ``max_distance`` and, where a candidate comes
    before that, by the overlaps of the frames in between.
    """
    timestamps = np.asarray(timestamps)
    count = len(poses)
    centres = poses[:, :3, 3]
    if count < 2 or not np.isfinite(centres).all():
        return label_covisible_pairs(overlap_matrix(grids, poses, camera, config), poses, timestamps, config)
    # Conservative: the exact test keeps a pair only when its float distance is <= max_distance; the
    # tree's own distance rounding (~1e-16 relative) is far inside the 1e-6 margin, so none is lost.
    near = cKDTree(centres).query_pairs(config.max_distance * (1 + 1e-6), output_type="ndarray")
    ref, query = near.min(axis=1), near.max(axis=1)
    # The exact tests of label_covisible_pairs, on the same float expressions.
    distance = np.linalg.norm(centres[query] - centres[ref], axis=1)
    keep = (distance <= config.max_distance) & (timestamps[query] - timestamps[ref] >= config.min_time_gap)
    query, ref = query[keep], ref[keep]
    projector = _Projector(grids, poses, camera, config)
    # Mutual overlap >= min_overlap: both directions are (min of two float32 values).
    keep = projector.pair_at_least(ref, query, config.min_overlap, every=1)
    query, ref = query[keep], ref[keep]
    keep = projector.pair_at_least(query, ref, config.min_overlap, every=1)
    query, ref = query[keep], ref[keep]
    # Having left: some frame j in (ref, query) is far from ref or overlaps it by < leave_overlap.
    refs, slot = np.unique(ref, return_inverse=True)
    far_first = _first_far(centres, refs, config.leave_factor * config.max_distance)
    pending = far_first[slot] >= query
    left = np.zeros(len(query), np.int64)
    left[pending] = _first_low_overlap(projector, ref[pending], query[pending], config)
    keep = left < query
    pairs = np.stack([query[keep], ref[keep]], axis=1).astype(np.int64)
    return pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]


def _first_far(centres: np.ndarray, refs: np.ndarray, radius: float) -> np.ndarray:
    """For each of ``refs``, the first later frame whose centre is farther than ``radius`` (N if none),
    with ``label_covisible_pairs``' distance expression."""
    count = len(centres)
    first = np.full(len(refs), count, np.int64)
    for k, r in enumerate(refs.tolist()):
        start, width = r + 1, 64
        while start < count:
            stop = min(count, start + width)
            far = np.flatnonzero(np.linalg.norm(centres[r] - centres[start:stop], axis=1) > radius)
            if far.size:
                first[k] = start + far[0]
                break
            start, width = stop, 2 * width
    return first


def _first_low_overlap(
    projector: _Projector, ref: np.ndarray, query: np.ndarray, config: CovisibilityLabelConfig
) -> np.ndarray:
    """For each pair, the first frame j in (ref, end) with mutual overlap < ``leave_overlap`` with
    ``ref``, ``end`` (the largest query of that ref) if none; compare with the pair's query."""
    refs, slot = np.unique(ref, return_inverse=True)
    ends = np.zeros(len(refs), np.int64)
    np.maximum.at(ends, slot, query)
    first = ends.copy()
    # The band (ref, end) of every ref: one direction, then the other up to its first low frame.
    for forward in (True, False):
        lengths = np.maximum(first - refs - 1, 0)
        offsets = np.repeat(np.cumsum(lengths) - lengths, lengths)
        band_ref = np.repeat(refs, lengths)
        band = np.arange(len(band_ref)) - offsets + band_ref + 1
        band_slot = np.repeat(np.arange(len(refs)), lengths)
        sources, targets = (band_ref, band) if forward else (band, band_ref)
        low = ~projector.pair_at_least(sources, targets, config.leave_overlap, every=4)
        np.minimum.at(first, band_slot[low], band[low])
    return first[slot]
