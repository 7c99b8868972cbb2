"""New map points from a new keyframe and its recent neighbours (guided matching, then DLT).

Brute-force matching of all unmapped keypoints of two keyframes costs tens of milliseconds, so the
search is guided by the known poses instead: each unmapped keypoint of the new keyframe is placed
at the keyframe's median scene depth and projected into the neighbour; candidates are the
neighbour's unmapped keypoints within ``search_fraction`` of the image diagonal of that prediction
(which covers the depth uncertainty along the epipolar line) and within ``epipolar_threshold``
sigmas of the epipolar line. Among those, the smallest Hamming distance wins if it passes the
distance limit and the ratio test. Triangulated points must lie in front of both cameras,
reproject within 2.45 sigma and show ``min_parallax_deg`` of parallax.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from frontends.mono_vo.config import KeyframeConfig
from frontends.mono_vo.features import best_two_per_group, octave_sigmas
from frontends.mono_vo.geometry import (
    check_triangulated,
    epipolar_distance,
    fundamental_from_poses,
    invert,
    linear_map,
    project,
    transform,
    triangulate,
)
from frontends.mono_vo.map import KeyframeState, SegmentMap
from frontends.orb import hamming, unique_targets


def triangulate_new_points(
    segment_map: SegmentMap,
    keyframe: KeyframeState,
    neighbour: KeyframeState,
    K: np.ndarray,
    octave_sigma: np.ndarray,
    settings: KeyframeConfig,
    max_error_sigmas: float,
    search_radius: float,
) -> int:
    """Add the points triangulated between two keyframes of ``segment_map``; returns how many."""
    free = np.flatnonzero((keyframe.point_ids < 0) & ~keyframe.dynamic)
    free_neighbour = np.flatnonzero((segment_map.live_ids(neighbour) < 0) & ~neighbour.dynamic)
    mapped = keyframe.point_ids >= 0
    if len(free) == 0 or len(free_neighbour) == 0 or not mapped.any():
        return 0
    depths = transform(keyframe.T_cw, segment_map.points.positions[keyframe.point_ids[mapped]])[:, 2]
    depth = float(np.median(depths[depths > 0])) if (depths > 0).any() else 1.0
    rays = linear_map(np.linalg.inv(K), np.column_stack([keyframe.features.points[free], np.ones(len(free))]))
    predicted, _ = project(K, neighbour.T_cw, transform(invert(keyframe.T_cw), rays * depth))
    inside = np.isfinite(predicted).all(axis=1)
    pairs = cKDTree(predicted[inside]).sparse_distance_matrix(
        cKDTree(neighbour.features.points[free_neighbour]), search_radius, output_type="ndarray"
    )
    own = free[np.flatnonzero(inside)[pairs["i"]]]
    other = free_neighbour[pairs["j"]]
    sigma = octave_sigmas(octave_sigma, keyframe.features.octaves[own])
    F = fundamental_from_poses(K, neighbour.T_cw, keyframe.T_cw)
    on_line = epipolar_distance(F, neighbour.features.points[other], keyframe.features.points[own]) < (
        settings.epipolar_threshold * sigma
    )
    own, other = own[on_line], other[on_line]
    distance = hamming(keyframe.features.descriptors[own], neighbour.features.descriptors[other])
    best, second = best_two_per_group(own, distance)
    accept = (distance[best] <= settings.match_max_hamming) & (distance[best] < settings.match_ratio * second)
    own, other = unique_targets(own[best][accept], other[best][accept], distance[best][accept])
    x_own, x_other = keyframe.features.points[own], neighbour.features.points[other]
    points_w = triangulate(K, neighbour.T_cw, keyframe.T_cw, x_other, x_own)
    sigma = octave_sigmas(octave_sigma, keyframe.features.octaves[own])
    good, _ = check_triangulated(
        K, (neighbour.T_cw, keyframe.T_cw), (x_other, x_own), points_w, max_error_sigmas * sigma,
        settings.min_parallax_deg,
    )  # fmt: skip
    ids = segment_map.points.add(points_w[good], keyframe.id)
    segment_map.observe(neighbour, other[good], ids)
    segment_map.observe(keyframe, own[good], ids)
    return len(ids)
