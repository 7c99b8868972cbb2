"""A loop constraint from two-view geometry, for a loop whose map is too thin for a Sim(3).

The verifier's Sim(3) needs ``min_points`` epipolar inliers with a map point in *both* keyframes.
Where tracking broke the map into short segments, two views of the same place often agree (hundreds
of epipolar inliers) while only a handful of inliers have a point in both maps (a real outdoor
sequence: 263 inliers, 6 in both). Each map still holds points of its own among the inliers, and
that is enough to join two segments as ORB-SLAM3 merges maps: the rotation R and the translation
direction t̂ come from the essential matrix (the verifier's two-view stage), the inliers
triangulated at a unit baseline (OpenCV) set each keyframe's own map points against it, which gives
the baseline in the query's units (λq, median depth ratio of the query's points) and in the match's
(λm). A query-camera point X then maps to s R X + t in the match camera with s = λm / λq and
t = λm t̂ (the verifier's ``relative`` convention).

Checked: a calibrated two-view fit, a median triangulation angle that fixes t̂, enough map points on
each side, and depth ratios that agree (each map is consistent with the two-view geometry up to its
scale). On gardens_point_day the joins between consecutive queries of one segment pair agree to
~1 deg and 5-10 % in scale. ``LoopClosing`` uses it only between segments that nothing joins yet and
only behind the bridge rule (a second consistent loop between the same segments).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from frontends.errors import ConfigError
from frontends.types import CameraIntrinsics, Keyframe


@dataclass(frozen=True)
class TwoViewJoinConfig:
    #: Join map segments with thin-map loops at all (False: such loops are only deferred).
    enabled: bool = True
    #: Median triangulation angle (deg) of the inliers needed to join (ORB-SLAM initialises from 1 deg).
    min_triangulation_angle_deg: float = 1.0
    #: Map points each keyframe must hold among the inliers (its own side of the scale).
    min_points: int = 10
    #: Share of each side's depth ratios that must lie within ``max_ratio_error`` of their median.
    min_consistent_ratio: float = 0.8
    #: Largest relative deviation of a depth ratio from their median.
    max_ratio_error: float = 0.25
    #: Rotation sigma (rad) of the join constraint (docs/2026-12-06-config-evidence.md)
    rotation_sigma: float = 0.02
    #: Translation sigma (fraction of the translation's length).
    translation_sigma: float = 0.25
    #: Floor of the translation sigma (fraction of the match's median point depth).
    min_translation_sigma: float = 0.05
    #: Floor of the log-scale sigma.
    min_log_scale_sigma: float = 0.05

    def __post_init__(self) -> None:
        if self.min_points < 3 or not 0 < self.min_consistent_ratio <= 1 or not self.max_ratio_error > 0:
            raise ConfigError(
                "two_view_join: min_points must be >= 3, min_consistent_ratio in (0, 1] and "
                "max_ratio_error > 0"
            )
        sigmas = (
            self.rotation_sigma,
            self.translation_sigma,
            self.min_translation_sigma,
            self.min_log_scale_sigma,
        )
        if not all(s > 0 for s in sigmas):
            raise ConfigError("two_view_join: the sigmas must be positive")


@dataclass(frozen=True)
class TwoViewJoin:
    """The constraint: ``relative`` (4x4 Sim(3), match_from_query) and its 7x7 covariance."""

    relative: np.ndarray
    covariance: np.ndarray
    #: (M, 2) keypoint indices (query, match) of the inliers whose map point fits the scale.
    correspondences: np.ndarray
    #: Map points of the query and of the match the scale rests on.
    points: tuple[int, int]


def two_view_join(
    query: Keyframe,
    match: Keyframe,
    pairs: np.ndarray,
    pose: np.ndarray | None,
    triangulation_angle_deg: float,
    camera: CameraIntrinsics,
    config: TwoViewJoinConfig = TwoViewJoinConfig(),
) -> TwoViewJoin | str:
    """The constraint from a passed two-view stage (its (K, 2) inlier keypoint ``pairs``, ``pose``
    = match_from_query [R | t] with |t| = 1, None without a calibrated fit, and the inliers' median
    triangulation angle) and each keyframe's own map points, or why there is none."""
    if pose is None:
        return "no calibrated two-view pose (a planar, panoramic or uncalibrated fit)"
    if triangulation_angle_deg < config.min_triangulation_angle_deg:
        return (
            f"triangulation angle {triangulation_angle_deg:.2f} deg < {config.min_triangulation_angle_deg:g}"
        )
    if query.points3d is None or match.points3d is None:
        return "no map points"
    if len(pairs) < config.min_points:
        return f"{len(pairs)} epipolar inliers < {config.min_points}"
    in_query, in_match = _unit_triangulation(query, match, pairs, pose, camera)
    front = (in_query[:, 2] > 0) & (in_match[:, 2] > 0)
    sides = []
    for name, mapped, unit in (
        ("query", query.points3d[pairs[:, 0]], in_query),
        ("match", match.points3d[pairs[:, 1]], in_match),
    ):
        held = front & np.isfinite(mapped).all(axis=1) & (mapped[:, 2] > 0)
        if held.sum() < config.min_points:
            return f"{int(held.sum())} {name} map points among the inliers < {config.min_points}"
        logs = np.full(len(pairs), np.nan)
        logs[held] = np.log(mapped[held, 2] / unit[held, 2])
        consistent = held & (np.abs(logs - np.nanmedian(logs)) <= np.log1p(config.max_ratio_error))
        if consistent.sum() < config.min_consistent_ratio * held.sum():
            return (
                f"{int(consistent.sum())} of {int(held.sum())} {name} map points fit one scale "
                f"(need ratio {config.min_consistent_ratio:g})"
            )
        sides.append((consistent, logs[consistent]))
    (query_fit, query_logs), (match_fit, match_logs) = sides
    query_unit, match_unit = float(np.exp(query_logs.mean())), float(np.exp(match_logs.mean()))
    relative = np.eye(4)
    relative[:3, :3] = match_unit / query_unit * pose[:, :3]
    relative[:3, 3] = match_unit * pose[:, 3]
    depth = float(np.median(match.points3d[pairs[match_fit, 1], 2]))
    translation_sigma = max(
        config.translation_sigma * float(np.linalg.norm(relative[:3, 3])),
        config.min_translation_sigma * depth,
    )
    log_scale_variance = max(
        float(np.var(query_logs) / len(query_logs) + np.var(match_logs) / len(match_logs)),
        config.min_log_scale_sigma**2,
    )
    variances = (config.rotation_sigma**2, translation_sigma**2, log_scale_variance)
    covariance = np.diag(np.repeat(variances, (3, 3, 1)))
    points = (len(query_logs), len(match_logs))
    return TwoViewJoin(relative, covariance, pairs[query_fit | match_fit], points)


def _unit_triangulation(
    query: Keyframe, match: Keyframe, pairs: np.ndarray, pose: np.ndarray, camera: CameraIntrinsics
) -> tuple[np.ndarray, np.ndarray]:
    """The inliers triangulated with the query camera at the origin and the match camera at
    ``pose`` (match_from_query, unit baseline): (K, 3) in the query's and the match's camera frame."""
    inverse = np.linalg.inv(camera.K)
    rays = [
        camera.undistort(keyframe.keypoints[indices]) @ inverse[:2, :2].T + inverse[:2, 2]
        for keyframe, indices in ((query, pairs[:, 0]), (match, pairs[:, 1]))
    ]
    homogeneous = cv2.triangulatePoints(np.eye(3, 4), pose, rays[0].T, rays[1].T)
    with np.errstate(divide="ignore", invalid="ignore"):
        in_query = (homogeneous[:3] / homogeneous[3]).T
    in_query[~np.isfinite(in_query).all(axis=1)] = np.nan
    return in_query, in_query @ pose[:, :3].T + pose[:, 3]
