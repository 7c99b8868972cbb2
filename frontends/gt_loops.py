"""Ground-truth loop labelling from ground-truth poses.

A frame ``q`` revisits an earlier frame ``r`` when the two cameras are close (position distance),
look the same way (angle between optical axes), and the camera has been away in between: it went
farther than ``leave_factor * max_distance`` from ``r`` before ``q`` and at least ``min_time_gap``
seconds passed. The "been away" rule keeps a camera that lingers in one place (a hand-held sensor
hovering over a desk) from labelling its own pass as a loop, whatever the frame rate.
Used for synthetic scenes and for real trajectories alike. The defaults suit indoor, hand-held
scales; for a car (KITTI) use ``max_distance`` of about 5-10 m.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from frontends.errors import DatasetError
from frontends.trajectory_io import read_numeric_table


@dataclass(frozen=True)
class LoopLabelConfig:
    #: Maximum camera-centre distance (m; in the trajectory's units).
    max_distance: float = 1.0
    #: Maximum angle between the two optical axes (deg).
    max_angle_deg: float = 30.0
    #: Minimum time between the two frames (s).
    min_time_gap: float = 10.0
    #: The camera must have gone farther than this multiple of ``max_distance`` from the reference.
    leave_factor: float = 2.0


def label_loop_pairs(
    poses: np.ndarray, timestamps: np.ndarray, config: LoopLabelConfig = LoopLabelConfig()
) -> np.ndarray:
    """All (query, reference) index pairs with query > reference that revisit, sorted.

    ``poses`` are camera-to-world 4x4 matrices (camera z axis = optical axis); frames whose pose is
    NaN (no ground truth) take part in no pair. Returns an (M, 2) int array.
    """
    poses = np.asarray(poses, dtype=np.float64)
    timestamps = np.asarray(timestamps, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(timestamps):
        raise ValueError("poses must be (N, 4, 4) and timestamps (N,)")
    valid = np.flatnonzero(np.isfinite(poses).all(axis=(1, 2)))
    if valid.size < 2:
        return np.zeros((0, 2), dtype=np.int64)
    centres = poses[valid, :3, 3]
    axes = poses[valid, :3, 2]
    axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
    pairs = cKDTree(centres).query_pairs(config.max_distance, output_type="ndarray")
    if pairs.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    later, earlier = pairs.max(axis=1), pairs.min(axis=1)  # cKDTree's pairs are i < j; be explicit
    query, ref = valid[later], valid[earlier]
    cos_angle = np.einsum("ij,ij->i", axes[later], axes[earlier])
    left = first_departure(centres, config.leave_factor * config.max_distance)
    keep = (
        (cos_angle >= np.cos(np.radians(config.max_angle_deg)))
        & (timestamps[query] - timestamps[ref] >= config.min_time_gap)
        & (left[earlier] < later)
    )
    result = np.stack([query[keep], ref[keep]], axis=1).astype(np.int64)
    order = np.lexsort((result[:, 1], result[:, 0]))
    return result[order]


def first_departure(centres: np.ndarray, radius: float, chunk: int = 256) -> np.ndarray:
    """For each position, the first later index farther than ``radius`` from it (len if never)."""
    n = len(centres)
    departure = np.full(n, n, dtype=np.int64)
    squared = np.einsum("ij,ij->i", centres, centres)
    later = np.arange(n)
    for start in range(0, n, chunk):
        block = centres[start : start + chunk]
        rows = np.arange(start, start + len(block))
        d2 = squared[rows, None] + squared[None, :] - 2.0 * block @ centres.T
        far = (d2 > radius * radius) & (later[None, :] > rows[:, None])
        departure[rows] = np.where(far.any(axis=1), far.argmax(axis=1), n)
    return departure


def read_loop_pairs(path: str | Path, num_frames: int | None = None) -> np.ndarray:
    """Read a ``query ref`` pairs file (0-based frame indices, ``#`` comments); validates indices."""
    table, lines = read_numeric_table(path, 2, error=DatasetError, allow_empty=True)
    if not np.all(table == np.round(table)):
        k = int(np.flatnonzero((table != np.round(table)).any(axis=1))[0])
        raise DatasetError(path, "frame indices must be integers", int(lines[k]))
    pairs = table.astype(np.int64)
    bad = np.flatnonzero(
        (pairs < 0).any(axis=1) | ((pairs >= num_frames).any(axis=1) if num_frames else False)
    )
    if bad.size:
        k = int(bad[0])
        raise DatasetError(
            path, f"frame index out of range 0..{(num_frames or 1) - 1}: {pairs[k].tolist()}", int(lines[k])
        )
    return pairs


def write_loop_pairs(path: str | Path, pairs: np.ndarray) -> None:
    lines = ["# query ref  (0-based frame indices; frame 'query' revisits the place seen in frame 'ref')"]
    lines += [f"{int(q)} {int(r)}" for q, r in np.asarray(pairs).reshape(-1, 2)]
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")
