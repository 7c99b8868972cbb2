"""ORB features and their matching for every stage: the frontend, the loop detectors, the
vocabulary and the verifier.

One extractor adapts to the image (measured in ``docs/2026-12-06-adaptive-orb.md``):

- **Two FAST thresholds per cell** (ORB-SLAM's ``iniThFAST``/``minThFAST``): corners are detected
  with ``fast_threshold``; in every ``cell_px`` cell where that finds fewer than
  ``min_cell_corners``, the cell's corners of ``min_fast_threshold`` are added. Low-contrast
  parts of an image (shade, sky edges, a dim corridor) still give features, textured parts keep
  their strong corners. OpenCV's ORB detects both sets (a mask restricts the second to the weak
  cells), so orientation, pyramid level and Harris response come from OpenCV.
- **A budget scaled by image area with a floor**: ``nfeatures`` is given for 640x480 (ORB-SLAM:
  1000 there, 2000 at KITTI's 1241x376), never fewer than ``min_nfeatures``: a 240x192 image has
  15 % of the area but needs enough matches to verify a loop or track.
- **Small images are detected at twice their size** (shorter side below ``upsample_below`` px):
  ORB's 31 px patch and border otherwise leave a 160x120 image a 96x56 inner area, and its coarse
  pyramid levels no room at all. Positions are reported in the original image.
- **Optional grid spreading** (``grid_cols`` x ``grid_rows``): the budget is picked round-robin
  over cells by response rank (tracking needs corners everywhere; place recognition measured
  better without, so the loop detectors keep the strongest corners).

OpenCV's ORB is deterministic; nothing here draws random numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

#: The image area ``OrbConfig.nfeatures`` is given for.
REFERENCE_AREA = 640 * 480


@dataclass(frozen=True)
class OrbConfig:
    #: Features per 640x480 image, scaled by image area (ORB-SLAM: 1000 at 640x480).
    nfeatures: int = 1000
    #: Never fewer features than this, whatever the image size (0: no floor).
    min_nfeatures: int = 500
    #: Scale the budget by image area (False: ``nfeatures`` for every size).
    scale_by_area: bool = True
    #: Pyramid scale factor between levels (ORB-SLAM 1.2).
    scale_factor: float = 1.2
    #: Pyramid levels (ORB-SLAM 8).
    levels: int = 8
    #: FAST threshold of the first pass (ORB-SLAM iniThFAST 20).
    fast_threshold: int = 20
    #: FAST threshold in cells where the first pass finds too few corners (ORB-SLAM minThFAST 7).
    min_fast_threshold: int = 7
    #: Side (px, level 0 of the detection image) of the cells the two thresholds are chosen in (ORB-SLAM 30).
    cell_px: int = 32
    #: A cell with fewer first-pass corners than this gets the second pass (ORB-SLAM 1; 0: no cells).
    min_cell_corners: int = 3
    #: Images whose shorter side is below this (px) are detected at twice their size (0: never).
    upsample_below: int = 240
    #: Corners detected per kept feature before spreading (only with a grid).
    overdetect: float = 3.0
    #: Grid for spreading features over the image (cells across and down); 0 disables it.
    grid_cols: int = 0
    #: Grid cells down (0 disables the grid).
    grid_rows: int = 0
    #: Border (px) without features; also the descriptor patch size (31 = ORB's).
    edge_threshold: int = 31

    def __post_init__(self) -> None:
        if self.nfeatures < 1 or self.levels < 1 or self.scale_factor <= 1.0:
            raise ValueError("ORB config: nfeatures and levels must be >= 1 and scale_factor > 1")
        if not 0 < self.min_fast_threshold <= self.fast_threshold:
            raise ValueError("ORB config: need 0 < min_fast_threshold <= fast_threshold")
        if self.grid_cols < 0 or self.grid_rows < 0 or self.min_nfeatures < 0 or self.upsample_below < 0:
            raise ValueError("ORB config: grid_cols, grid_rows, min_nfeatures, upsample_below must be >= 0")
        if self.cell_px < 8 or self.min_cell_corners < 0 or self.overdetect < 1.0:
            raise ValueError("ORB config: need cell_px >= 8, min_cell_corners >= 0, overdetect >= 1")
        if self.edge_threshold < 3:
            raise ValueError("ORB config: edge_threshold must be >= 3")

    def features_for(self, width: int, height: int) -> int:
        """The feature budget of a ``width`` x ``height`` image (the floor never exceeds ``nfeatures``)."""
        if not self.scale_by_area:
            return self.nfeatures
        scaled = round(self.nfeatures * width * height / REFERENCE_AREA)
        return max(1, min(self.nfeatures, self.min_nfeatures), scaled)

    def upsampled(self, width: int, height: int) -> bool:
        """Whether a ``width`` x ``height`` image is detected at twice its size."""
        return min(width, height) < self.upsample_below


#: Tracking (mono-vo): corners everywhere. A denser budget (ORB-SLAM uses 1000-2000), spread over a
#: 16x12 grid, weak cells re-detected at the low threshold; no upsampling, so a keypoint's pyramid
#: level keeps meaning ``scale_factor ** level`` pixels of position noise.
TRACKING_ORB = OrbConfig(
    nfeatures=1500, min_nfeatures=1000, overdetect=1.5, grid_cols=16, grid_rows=12, min_cell_corners=3,
    upsample_below=0,
)  # fmt: skip


@dataclass(frozen=True)
class OrbFeatures:
    """ORB keypoints of one image: positions, descriptors and the keypoint attributes."""

    #: (N, 2) float32 pixel positions (x, y) in the image given.
    keypoints: np.ndarray
    #: (N, 32) uint8 rBRIEF descriptors.
    descriptors: np.ndarray
    #: (N,) float32 diameter of the keypoint neighbourhood (px in the image given).
    sizes: np.ndarray
    #: (N,) float32 orientation (deg).
    angles: np.ndarray
    #: (N,) int32 pyramid level.
    octaves: np.ndarray
    #: (N,) float32 Harris response.
    responses: np.ndarray

    def __len__(self) -> int:
        return len(self.keypoints)


def detect_orb(gray: np.ndarray, config: OrbConfig = OrbConfig()) -> OrbFeatures:
    """ORB features of an 8-bit grey image (a BGR image is converted); empty arrays when there are none."""
    image = np.asarray(gray)
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"detect_orb needs an 8-bit grey image, got {image.dtype} {image.shape}")
    height, width = image.shape
    budget = config.features_for(width, height)
    factor = 2 if config.upsampled(width, height) else 1
    if factor != 1:
        image = cv2.resize(image, (width * factor, height * factor), interpolation=cv2.INTER_LINEAR)
    spread = config.grid_cols > 0 and config.grid_rows > 0
    # Over-detect when spreading: the cells choose from more corners than the budget.
    detect_count = max(budget, round(budget * config.overdetect)) if spread else budget
    keypoints, descriptors = _detect(image, config, config.fast_threshold, detect_count, None)
    first = len(keypoints)
    if config.min_fast_threshold < config.fast_threshold and (spread or len(keypoints) < budget):
        # Too few corners overall: the whole image again at the lower threshold (as before the
        # cells); else only the weak cells (a textured image that fills the budget without a
        # grid keeps its strongest corners, so the second pass is skipped there).
        whole = len(keypoints) < budget // 2
        mask = None if whole else _weak_cells_mask(image.shape, keypoints, config)
        if whole or mask is not None:
            more, more_descriptors = _detect(image, config, config.min_fast_threshold, detect_count, mask)
            first = 0 if whole else first
            keypoints, descriptors = (more, more_descriptors) if whole else (
                keypoints + more, np.concatenate([descriptors, more_descriptors]),
            )  # fmt: skip
    if not keypoints:
        return _empty()
    xy = np.array([k.pt for k in keypoints], dtype=np.float64).reshape(-1, 2)
    response = np.array([k.response for k in keypoints], dtype=np.float64)
    # Corners of the first pass are chosen before those of the weak cells' second pass: the low
    # threshold fills the budget where the image lacks strong corners, it never displaces them
    # (displacing them cost tracking on KITTI; docs/2026-12-06-adaptive-orb.md).
    keep = _choose(xy[:first], response[:first], image.shape, budget, config, spread)
    if len(keep) < budget and len(keypoints) > first:
        extra = _choose(xy[first:], response[first:], image.shape, budget - len(keep), config, spread)
        keep = np.sort(np.concatenate([keep, first + extra]))
    chosen = [keypoints[i] for i in keep]
    return OrbFeatures(
        keypoints=(xy[keep] / factor).astype(np.float32),
        descriptors=np.ascontiguousarray(descriptors[keep], dtype=np.uint8),
        sizes=np.array([k.size / factor for k in chosen], dtype=np.float32),
        angles=np.array([k.angle for k in chosen], dtype=np.float32),
        octaves=np.array([k.octave for k in chosen], dtype=np.int32),
        responses=response[keep].astype(np.float32),
    )


def extract_orb(gray: np.ndarray, config: OrbConfig = OrbConfig()) -> tuple[np.ndarray, np.ndarray]:
    """``(keypoints (N, 2) float32, descriptors (N, 32) uint8)`` of an 8-bit grey image."""
    features = detect_orb(gray, config)
    return features.keypoints, features.descriptors


def spread_over_grid(
    xy: np.ndarray, response: np.ndarray, width: int, height: int, cols: int, rows: int, budget: int
) -> np.ndarray:
    """Indices of ``budget`` keypoints taken round-robin over grid cells, strongest first in each cell."""
    if len(xy) <= budget or cols < 1 or rows < 1:
        return np.arange(len(xy))
    col = np.clip((xy[:, 0] * cols / width).astype(np.int64), 0, cols - 1)
    row = np.clip((xy[:, 1] * rows / height).astype(np.int64), 0, rows - 1)
    cell = row * cols + col
    order = np.lexsort((-response, cell))
    sorted_cell = cell[order]
    rank = np.arange(len(order)) - np.searchsorted(sorted_cell, sorted_cell, side="left")
    # Round r takes the r-th strongest corner of every cell; within a round the strongest go first.
    picked = order[np.lexsort((-response[order], rank))[:budget]]
    return np.sort(picked)


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise Hamming distance of two (K, 32) uint8 descriptor arrays."""
    words_a = np.ascontiguousarray(a).view(np.uint64)
    words_b = np.ascontiguousarray(b).view(np.uint64)
    return np.bitwise_count(words_a ^ words_b).sum(axis=1, dtype=np.int64)


def match_descriptors(
    query: np.ndarray, train: np.ndarray, ratio: float, max_hamming: int, *, mutual: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force Hamming matches (OpenCV) passing Lowe's ratio test and ``max_hamming``:
    (query index, train index) arrays, one query per train descriptor (the closest). ``mutual``:
    only pairs that are also each other's nearest neighbour from the train side (the verifier's
    check; the tracker's candidates are further filtered by geometry instead)."""
    none = np.zeros(0, np.int64)
    if len(query) < 2 or len(train) < 2:
        return none, none
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    pairs = matcher.knnMatch(query, train, k=2)
    rows = np.array(
        [(m[0].queryIdx, m[0].trainIdx, m[0].distance, m[1].distance) for m in pairs if len(m) == 2],
        dtype=np.float64,
    ).reshape(-1, 4)
    rows = rows[(rows[:, 2] <= max_hamming) & (rows[:, 2] < ratio * rows[:, 3])]
    source, target = unique_targets(rows[:, 0].astype(np.int64), rows[:, 1].astype(np.int64), rows[:, 2])
    if not mutual or len(target) == 0:
        return source, target
    # The backward match of only the train descriptors that passed: the same answer as a full
    # second pass (each row is matched on its own) at a fraction of its cost.
    best_back = np.full(len(train), -1, dtype=np.int64)
    for m in matcher.match(train[target], query):
        best_back[target[m.queryIdx]] = m.trainIdx
    keep = np.flatnonzero(best_back[target] == source)
    keep = keep[np.argsort(source[keep], kind="stable")]  # in query order
    return source[keep], target[keep]


def group_order(group: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """``np.lexsort((distance, group))``: by group, then distance, ties in input order. Integer
    distances (Hamming) sort as one key, ~1.6x faster (the tracker runs it several times per frame)."""
    if np.issubdtype(distance.dtype, np.integer) and len(distance) and distance.min() >= 0:
        span = int(distance.max()) + 1
        if max(abs(int(group.min())), abs(int(group.max()))) < np.iinfo(np.int64).max // (2 * span):
            return np.argsort(group.astype(np.int64) * span + distance, kind="stable")
    return np.lexsort((distance, group))


def unique_targets(
    source: np.ndarray, target: np.ndarray, distance: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Keep one match per target: the one with the smallest distance."""
    order = group_order(target, distance)
    sorted_target = target[order]
    first = order[np.r_[True, sorted_target[1:] != sorted_target[:-1]]] if len(order) else order
    return source[first], target[first]


def _choose(
    xy: np.ndarray, response: np.ndarray, shape: tuple[int, ...], budget: int, config: OrbConfig, spread: bool
) -> np.ndarray:
    """Indices of at most ``budget`` corners: spread over the grid, or the strongest by response."""
    if spread:
        return spread_over_grid(xy, response, shape[1], shape[0], config.grid_cols, config.grid_rows, budget)
    if len(xy) > budget:
        return np.sort(np.argsort(-response, kind="stable")[:budget])
    return np.arange(len(xy))


def _weak_cells_mask(
    shape: tuple[int, ...], keypoints: list[cv2.KeyPoint], config: OrbConfig
) -> np.ndarray | None:
    """A detection mask of the cells (inside the border) with fewer than ``min_cell_corners``
    first-pass corners, or None when there is no such cell."""
    height, width = shape[:2]
    cell = config.cell_px
    cols, rows = max(1, -(-width // cell)), max(1, -(-height // cell))
    counts = np.zeros((rows, cols), np.int64)
    if keypoints:
        xy = np.array([k.pt for k in keypoints], dtype=np.float64).reshape(-1, 2)
        np.add.at(
            counts,
            (np.clip((xy[:, 1] // cell).astype(np.int64), 0, rows - 1),
             np.clip((xy[:, 0] // cell).astype(np.int64), 0, cols - 1)),
            1,
        )  # fmt: skip
    weak = counts < config.min_cell_corners
    if not weak.any():
        return None
    mask = np.kron(weak.astype(np.uint8) * 255, np.ones((cell, cell), np.uint8))[:height, :width]
    return np.ascontiguousarray(mask)


def _orb(config: OrbConfig, fast_threshold: int, nfeatures: int) -> cv2.ORB:
    return cv2.ORB.create(
        nfeatures=max(1, nfeatures),
        scaleFactor=config.scale_factor,
        nlevels=config.levels,
        edgeThreshold=config.edge_threshold,
        patchSize=31,
        fastThreshold=fast_threshold,
    )


def _detect(
    image: np.ndarray, config: OrbConfig, fast_threshold: int, count: int, mask: np.ndarray | None
) -> tuple[list[cv2.KeyPoint], np.ndarray]:
    """Keypoints and descriptors in one pyramid pass (OpenCV drops those too near the border)."""
    keypoints, descriptors = _orb(config, fast_threshold, count).detectAndCompute(image, mask)
    if descriptors is None or not keypoints:
        return [], np.zeros((0, 32), np.uint8)
    return list(keypoints), descriptors


def _empty() -> OrbFeatures:
    return OrbFeatures(
        keypoints=np.zeros((0, 2), np.float32),
        descriptors=np.zeros((0, 32), np.uint8),
        sizes=np.zeros(0, np.float32),
        angles=np.zeros(0, np.float32),
        octaves=np.zeros(0, np.int32),
        responses=np.zeros(0, np.float32),
    )
