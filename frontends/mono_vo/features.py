"""ORB features spread over the image, and the descriptor matching the tracker needs.

Extraction: ``frontends.orb`` (shared with the loop detectors and the verifier) with the tracking
preset: ``overdetect`` x the budget, two FAST thresholds per cell, then the features are picked
round-robin over a grid of cells by response rank. ORB-SLAM spreads its features with a per-level
quadtree for the same reason: tracking and PnP need corners everywhere, not only in the most
textured patch.

Matching: ``match_in_radius`` pairs projected map points with keypoints within a pixel radius (a
k-d tree gives the candidate pairs in C), takes the Hamming distance of every candidate pair
(``frontends.orb.hamming``: ``np.bitwise_count`` on 64-bit words), and keeps the best pair per
point when it passes the distance limit and Lowe's ratio test, one point per keypoint. No Python
loop runs per point. Only keypoints within one pyramid level of the point's predicted level are
candidates (ORB-SLAM's scale prediction): in repetitive texture a wrong patch nearby often matches
a descriptor well, but seldom at the right scale. ``consistent_rotation`` is ORB-SLAM's orientation
histogram over the matches.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from frontends.base import LOOKAHEAD_FRAMES
from frontends.orb import OrbConfig, detect_orb, group_order, hamming, unique_targets
from frontends.types import CameraIntrinsics


@dataclass(frozen=True)
class Features:
    """ORB features of one image."""

    #: (N, 2) float32 pixel positions as detected (distorted image).
    keypoints: np.ndarray
    #: (N, 2) float64 positions in the undistorted image (what the geometry uses).
    points: np.ndarray
    #: (N, 32) uint8 descriptors.
    descriptors: np.ndarray
    #: (N,) int pyramid level.
    octaves: np.ndarray
    #: (N,) float orientation (deg) of the descriptor's patch.
    angles: np.ndarray

    def __len__(self) -> int:
        return len(self.keypoints)

    def subset(self, index: np.ndarray) -> Features:
        return Features(
            self.keypoints[index], self.points[index], self.descriptors[index], self.octaves[index],
            self.angles[index],
        )  # fmt: skip


def empty_features() -> Features:
    return Features(
        np.zeros((0, 2), np.float32), np.zeros((0, 2)), np.zeros((0, 32), np.uint8),
        np.zeros(0, np.int64), np.zeros(0),
    )  # fmt: skip


class OrbExtractor:
    """``frontends.orb`` features of one camera's images, with the keypoints undistorted."""

    def __init__(self, settings: OrbConfig, camera: CameraIntrinsics) -> None:
        self.settings = settings
        self.camera = camera
        self.budget = settings.features_for(camera.width, camera.height)

    def extract(self, gray: np.ndarray) -> Features:
        found = detect_orb(gray, self.settings)
        if len(found) == 0:
            return empty_features()
        return Features(
            found.keypoints, self.camera.undistort(found.keypoints), found.descriptors,
            found.octaves.astype(np.int64), found.angles.astype(np.float64),
        )  # fmt: skip


def octave_sigmas(octave_sigma: np.ndarray, octaves: np.ndarray) -> np.ndarray:
    """Position noise of keypoints found on pyramid levels ``octaves`` (the level's scale factor,
    ``octave_sigma`` per level; levels past its end take the last)."""
    return octave_sigma[np.minimum(octaves, len(octave_sigma) - 1)]


def match_in_radius(
    projected: np.ndarray,
    point_descriptors: np.ndarray,
    point_levels: np.ndarray,
    keypoint_tree: cKDTree,
    features: Features,
    radius: float,
    max_hamming: int,
    ratio: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Match projected points to keypoints within ``radius`` px: (point index, keypoint index) arrays.

    A point is only compared with keypoints detected within one pyramid level of its predicted level
    ``point_levels`` (what its distance from the camera implies for the patch its descriptor shows).
    """
    none = np.zeros(0, np.int64)
    if len(projected) == 0 or keypoint_tree.n == 0:
        return none, none
    pairs = cKDTree(projected).sparse_distance_matrix(keypoint_tree, radius, output_type="ndarray")
    point = pairs["i"].astype(np.int64)
    keypoint = pairs["j"].astype(np.int64)
    same_scale = np.abs(features.octaves[keypoint] - point_levels[point]) <= 1
    point, keypoint = point[same_scale], keypoint[same_scale]
    if len(point) == 0:
        return none, none
    distance = hamming(point_descriptors[point], features.descriptors[keypoint])
    best, second = best_two_per_group(point, distance)
    accept = (distance[best] <= max_hamming) & (distance[best] < ratio * second)
    return unique_targets(point[best][accept], keypoint[best][accept], distance[best][accept])


def consistent_rotation(angle_difference: np.ndarray, bins: int, min_share: float) -> np.ndarray:
    """ORB-SLAM's rotation check: which matches fall in the three most popular bins of the keypoint
    angle differences (deg). True matches share the camera's roll; false ones scatter. The second and
    third bins count only with ``min_share`` of the first's matches."""
    if len(angle_difference) == 0:
        return np.zeros(0, bool)
    index = (np.mod(angle_difference, 360.0) * bins / 360.0).astype(np.int64) % bins
    counts = np.bincount(index, minlength=bins)
    top = np.argsort(-counts, kind="stable")[:3]
    kept = top[counts[top] >= max(1.0, min_share * counts[top[0]])]
    return np.isin(index, kept)


def best_two_per_group(group: np.ndarray, distance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per group: the index of its smallest distance and the second smallest distance (inf if none)."""
    if len(group) == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    order = group_order(group, distance)
    sorted_group = group[order]
    first = np.flatnonzero(np.r_[True, sorted_group[1:] != sorted_group[:-1]])
    has_second = np.r_[first[1:], len(order)] - first > 1
    second = np.full(len(first), np.inf)
    second[has_second] = distance[order[first[has_second] + 1]]
    return order[first], second


#: Prefetched frames an extractor holds at most (the newest).
MAX_PREFETCHED = 2 * LOOKAHEAD_FRAMES


class PrefetchingExtractor:
    """An ``OrbExtractor`` that can run frames ahead on a worker thread.

    OpenCV releases the GIL, so the next frames' ORB runs on the second core while this frame is
    tracked (bundle adjustment in GTSAM holds the GIL, extraction does not need it). Every extraction
    runs on the one worker thread, because a ``cv2.ORB`` must not be used by two threads at once;
    the features are those of inline extraction, so runs stay deterministic. Pending work does not
    pickle (checkpoints): a restored extractor simply extracts the next frame when it comes.
    """

    def __init__(self, extractor: OrbExtractor) -> None:
        self.extractor = extractor
        self._worker: ThreadPoolExecutor | None = None
        #: Frames handed to ``prefetch`` (matched by identity), oldest first, with their features
        #: being computed: the current frame's and the next ones' (``frontends.base.with_lookahead``).
        self._pending: list[tuple[object, Future[Features]]] = []

    def prefetch(self, frame: object, gray: Callable[[], np.ndarray]) -> None:
        # Bounded: frames prefetched but never tracked (a caller that skips them) do not pile up.
        self._pending = [*self._pending[-MAX_PREFETCHED + 1 :], (frame, self._submit(gray))]

    def extract(self, frame: object, gray: Callable[[], np.ndarray]) -> Features:
        for position, (pending, future) in enumerate(self._pending):
            if pending is frame:
                del self._pending[: position + 1]
                return future.result()
        return self._submit(gray).result()

    def _submit(self, gray: Callable[[], np.ndarray]) -> Future[Features]:
        if self._worker is None:
            self._worker = ThreadPoolExecutor(1, thread_name_prefix="orb")
        return self._worker.submit(lambda: self.extractor.extract(gray()))

    def __getstate__(self) -> dict[str, Any]:
        return {"extractor": self.extractor}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["extractor"])  # type: ignore[misc]
