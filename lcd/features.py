"""ORB features shared by the loop detectors and the vocabulary trainer.

Choices (measured in ``lcd/data/README.md`` and the vBoW report):

- ``nfeatures`` is given for a 640x480 image and scaled by image area (``scale_by_area``), so a
  KITTI frame (1226x370, 1.5x the area) gets 1.5x the features and a 320x240 test scene a quarter:
  the feature *density* stays what the thresholds were chosen for. ORB-SLAM uses 1000 at 640x480
  and 2000 at KITTI size, i.e. the same rule; our default of 1000 follows it.
- FAST threshold 20 with a retry at 7 where the image yields too few corners (ORB-SLAM's
  ``iniThFAST``/``minThFAST``): low-texture images still give features, textured ones keep the
  stronger corners.
- Grid spreading (``grid_cols`` x ``grid_rows`` cells; off by default): ORB-SLAM spreads features
  over the image (its quadtree) for tracking; here corners are over-detected and then picked
  round-robin across the cells by response rank. For place recognition it *hurt*: 8x6 cells cost
  0.04-0.14 recall at 100 % precision on the RTAB-Map samples and up to 0.2 top-1 accuracy on a
  synthetic figure-8 scene (weak corners in flat cells are unstable words), so it is off.
- 8 pyramid levels at scale factor 1.2 (ORB-SLAM's and OpenCV's defaults).

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
    #: Features per 640x480 image (scaled by image area when ``scale_by_area``).
    nfeatures: int = 1000
    scale_by_area: bool = True
    scale_factor: float = 1.2
    levels: int = 8
    #: FAST threshold; ``min_fast_threshold`` is tried when fewer than half the features are found.
    fast_threshold: int = 20
    min_fast_threshold: int = 7
    #: Grid for spreading features over the image (cells across and down); 0 disables it.
    grid_cols: int = 0
    grid_rows: int = 0
    #: Border (px) without features; also the descriptor patch size (31 = ORB's).
    edge_threshold: int = 31

    def __post_init__(self) -> None:
        if self.nfeatures < 1 or self.levels < 1 or self.scale_factor <= 1.0:
            raise ValueError("ORB config: nfeatures and levels must be >= 1 and scale_factor > 1")
        if not 0 < self.min_fast_threshold <= self.fast_threshold:
            raise ValueError("ORB config: need 0 < min_fast_threshold <= fast_threshold")
        if self.grid_cols < 0 or self.grid_rows < 0:
            raise ValueError("ORB config: grid_cols and grid_rows must be >= 0")

    def features_for(self, width: int, height: int) -> int:
        """The feature budget of a ``width`` x ``height`` image."""
        if not self.scale_by_area:
            return self.nfeatures
        return max(1, round(self.nfeatures * width * height / REFERENCE_AREA))


@dataclass(frozen=True)
class OrbFeatures:
    """ORB keypoints of one image: positions, descriptors and the keypoint attributes."""

    #: (N, 2) float32 pixel positions (x, y).
    keypoints: np.ndarray
    #: (N, 32) uint8 rBRIEF descriptors.
    descriptors: np.ndarray
    #: (N,) float32 diameter of the keypoint neighbourhood (px), grows with the pyramid level.
    sizes: np.ndarray
    #: (N,) float32 orientation (deg).
    angles: np.ndarray
    #: (N,) int32 pyramid level.
    octaves: np.ndarray
    #: (N,) float32 FAST/Harris response.
    responses: np.ndarray


def detect_orb(gray: np.ndarray, config: OrbConfig = OrbConfig()) -> OrbFeatures:
    """ORB features of an 8-bit grey image (a BGR image is converted); empty arrays when there are none."""
    image = np.asarray(gray)
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2 or image.dtype != np.uint8:
        raise ValueError(f"detect_orb needs an 8-bit grey image, got {image.dtype} {image.shape}")
    height, width = image.shape
    budget = config.features_for(width, height)
    spread = config.grid_cols > 0 and config.grid_rows > 0
    # Over-detect when spreading so that the sparse cells have corners to offer.
    detect_count = 3 * budget if spread else budget
    keypoints = _detect(image, config, config.fast_threshold, detect_count)
    if len(keypoints) < budget // 2 and config.min_fast_threshold < config.fast_threshold:
        keypoints = _detect(image, config, config.min_fast_threshold, detect_count)
    if spread and len(keypoints) > budget:
        keypoints = _spread(keypoints, width, height, config.grid_cols, config.grid_rows, budget)
    if not keypoints:
        return _empty()
    orb = _orb(config, config.fast_threshold, len(keypoints))
    described, descriptors = orb.compute(image, keypoints)
    if descriptors is None or not described:
        return _empty()
    return OrbFeatures(
        keypoints=np.array([k.pt for k in described], dtype=np.float32).reshape(-1, 2),
        descriptors=np.ascontiguousarray(descriptors, dtype=np.uint8),
        sizes=np.array([k.size for k in described], dtype=np.float32),
        angles=np.array([k.angle for k in described], dtype=np.float32),
        octaves=np.array([k.octave for k in described], dtype=np.int32),
        responses=np.array([k.response for k in described], dtype=np.float32),
    )


def extract_orb(gray: np.ndarray, config: OrbConfig = OrbConfig()) -> tuple[np.ndarray, np.ndarray]:
    """``(keypoints (N, 2) float32, descriptors (N, 32) uint8)`` of an 8-bit grey image."""
    features = detect_orb(gray, config)
    return features.keypoints, features.descriptors


def _orb(config: OrbConfig, fast_threshold: int, nfeatures: int) -> cv2.ORB:
    return cv2.ORB.create(
        nfeatures=nfeatures,
        scaleFactor=config.scale_factor,
        nlevels=config.levels,
        edgeThreshold=config.edge_threshold,
        patchSize=config.edge_threshold,
        fastThreshold=fast_threshold,
    )


def _detect(image: np.ndarray, config: OrbConfig, fast_threshold: int, count: int) -> list[cv2.KeyPoint]:
    return list(_orb(config, fast_threshold, count).detect(image, None))


def _spread(
    keypoints: list[cv2.KeyPoint], width: int, height: int, cols: int, rows: int, budget: int
) -> list[cv2.KeyPoint]:
    """Pick ``budget`` keypoints round-robin over grid cells, strongest first within each cell."""
    xy = np.array([k.pt for k in keypoints], dtype=np.float64)
    response = np.array([k.response for k in keypoints], dtype=np.float64)
    col = np.clip((xy[:, 0] * cols / width).astype(np.int64), 0, cols - 1)
    row = np.clip((xy[:, 1] * rows / height).astype(np.int64), 0, rows - 1)
    cell = row * cols + col
    order = np.lexsort((-response, cell))
    sorted_cell = cell[order]
    first_of_cell = np.searchsorted(sorted_cell, sorted_cell, side="left")
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order)) - first_of_cell
    # Round r takes the r-th strongest corner of every cell; within a round the strongest go first.
    chosen = np.lexsort((-response, rank))[:budget]
    return [keypoints[i] for i in np.sort(chosen)]


def _empty() -> OrbFeatures:
    return OrbFeatures(
        keypoints=np.zeros((0, 2), np.float32),
        descriptors=np.zeros((0, 32), np.uint8),
        sizes=np.zeros(0, np.float32),
        angles=np.zeros(0, np.float32),
        octaves=np.zeros(0, np.int32),
        responses=np.zeros(0, np.float32),
    )
