"""Global bundle adjustment after loop closing (ORB-SLAM's full BA after the pose graph).

The pose graph moves each keyframe as a whole; what its map points say about the poses between
loops is summarised by one odometry covariance per step. Full bundle adjustment over every
keyframe and map point, started at the pose graph's estimate, uses them all, and ties the two
visits of a loop through the map itself: the query keyframe also observes the match keyframe's
points at the keypoints the verifier paired with them (and the match the query's), as ORB-SLAM
fuses the duplicated points of a loop.

Input is frontend-agnostic: keyframes with ``point_ids`` (map point of each keypoint, unique within
the keyframe's segment) and ``points3d`` (its camera-frame position in the keyframe's units), the
backend's camera-to-world Sim(3) estimate of each, and the verified correspondences of the accepted
loops. A point starts where its oldest observing keyframe's estimate puts it. Variables are the
keyframes' SE(3) poses and the points' world positions, factors GTSAM projection factors on
undistorted pixels with a Huber kernel, each with its keypoint's sigma (``Keyframe.keypoint_sigmas``:
an ORB keypoint found on a coarser pyramid level is located less precisely, as in the frontend's
local bundle adjustment). Gauge: in each connected part of the map (keyframes sharing
points), the oldest keyframe is fixed and the distance to the next one is kept (the scale).

Afterwards each keyframe's Sim(3) is its adjusted pose with the scale that maps its ``points3d``
onto the adjusted points (median distance ratio), so frames posed relative to a keyframe (in its
units) follow it. A keyframe without points keeps the pose graph's estimate.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
import pycolmap
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from frontends.base import PointObservations
from frontends.errors import ConfigError
from frontends.types import CameraIntrinsics, Keyframe
from slam_backend.lie import as_4x4

log = logging.getLogger(__name__)

_FIXED_SIGMA = 1e-6


@dataclass(frozen=True)
class GlobalBundleAdjustmentConfig:
    #: Run it when the stream ends, if any loop was accepted.
    enabled: bool = True
    #: Keypoint position noise (px) at the finest detection scale (times the keyframe's
    #: ``keypoint_sigmas`` where it has them) and the Huber kernel's threshold in sigmas (chi2 95 %,
    #: 2 dof).
    pixel_sigma: float = 1.0
    huber_k: float = 2.447
    #: Levenberg-Marquardt stops after this many iterations or when one gains less than this
    #: (20 and 1e-4 gave the same ATE on the benchmark scenes within 0.2 mm, at up to 2.3x the time).
    iterations: int = 10
    relative_error_tolerance: float = 1e-3
    #: Points observed by fewer keyframes do not constrain poses.
    min_observations: int = 2
    #: Every frame the frontend posed from map points is posed again against the adjusted points
    #: (``repose_frame``) when at least ``frame_min_inliers`` of them fit within
    #: ``frame_max_error_px``; otherwise it follows its keyframes.
    repose_frames: bool = True
    frame_min_inliers: int = 20
    frame_max_error_px: float = 4.0
    frame_search_factor: float = 3.0

    def __post_init__(self) -> None:
        if self.pixel_sigma <= 0 or self.huber_k <= 0:
            raise ConfigError("global_ba: pixel_sigma and huber_k must be positive")
        if self.iterations < 1 or self.min_observations < 2:
            raise ConfigError("global_ba: iterations must be >= 1 and min_observations >= 2")


@dataclass(frozen=True)
class LoopCorrespondences:
    """Keypoint pairs of one accepted loop: (M, 2) indices into the query's and the match's keypoints."""

    query: int
    match: int
    pairs: np.ndarray


@dataclass(frozen=True)
class GlobalBundleAdjustmentStats:
    keyframes: int
    points: int
    observations: int
    loop_observations: int
    #: Median reprojection error (px) of all observations before and after.
    median_error_before_px: float
    median_error_after_px: float


@dataclass(frozen=True)
class AdjustedMap:
    """The outcome: keyframe poses and the map points they were adjusted with."""

    #: Camera-to-world Sim(3) of every keyframe of the input estimates (unchanged where the map
    #: said nothing about it).
    poses: dict[int, np.ndarray]
    #: Row in ``points`` of each (segment, point id).
    point_rows: dict[tuple[int, int], int]
    #: (P, 3) adjusted world positions, NaN for points that were not adjusted.
    points: np.ndarray
    stats: GlobalBundleAdjustmentStats

    def positions(self, segment: int, point_ids: np.ndarray) -> np.ndarray:
        """World positions of a segment's points (NaN rows for points the adjustment left out)."""
        rows = np.array([self.point_rows.get((segment, i), -1) for i in point_ids.tolist()], np.int64)
        result = np.full((len(rows), 3), np.nan)
        known = rows >= 0
        result[known] = self.points[rows[known]]
        return result


def global_bundle_adjustment(
    keyframes: Sequence[Keyframe],
    estimates: Mapping[int, np.ndarray],
    loops: Sequence[LoopCorrespondences],
    camera: CameraIntrinsics,
    config: GlobalBundleAdjustmentConfig = GlobalBundleAdjustmentConfig(),
) -> AdjustedMap | None:
    """The adjusted map, None when there was nothing to adjust (or the optimisation failed)."""
    by_id = {kf.id: kf for kf in keyframes if kf.id in estimates and kf.point_ids is not None}
    observed = _collect_observations(by_id, loops, camera)
    if observed is None:
        return None
    keyframe_ids, keypoint_xy, point_index = observed.keyframe_ids, observed.xy, observed.point_index
    point_keys = observed.keys
    positions = _initial_points(by_id, estimates, observed)
    seen = np.bincount(point_index, minlength=len(point_keys))
    # Keyframes seeing the same point twice (a loop observation) still count once here: close enough.
    kept = np.isfinite(positions).all(axis=1) & (seen >= config.min_observations)
    keep_observation = kept[point_index]
    keyframe_ids, keypoint_xy, point_index = (
        keyframe_ids[keep_observation], keypoint_xy[keep_observation], point_index[keep_observation]
    )  # fmt: skip
    sigmas = observed.sigma[keep_observation]
    if len(point_index) == 0:
        return None
    poses = {k: as_4x4(estimates[k]) for k in np.unique(keyframe_ids).tolist()}

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    calibration = gtsam.Cal3_S2(camera.fx, camera.fy, 0.0, camera.cx, camera.cy)
    for kf_id, pose in poses.items():
        values.insert(gtsam.symbol("x", kf_id), gtsam.Pose3(pose))
    used = np.unique(point_index)
    for index in used.tolist():
        values.insert(index, positions[index])
    noise_by_sigma: dict[float, gtsam.noiseModel.Base] = {}
    for kf_id in poses:
        chosen = np.flatnonzero(keyframe_ids == kf_id)
        # One batch of factors per keypoint sigma (ORB: per pyramid level) of this keyframe.
        for sigma in np.unique(sigmas[chosen]).tolist():
            if sigma not in noise_by_sigma:
                noise_by_sigma[sigma] = gtsam.noiseModel.Robust.Create(
                    gtsam.noiseModel.mEstimator.Huber.Create(config.huber_k),
                    gtsam.noiseModel.Isotropic.Sigma(2, config.pixel_sigma * sigma),
                )
            level = chosen[sigmas[chosen] == sigma]
            gtsam.utilities.insertProjectionFactors(
                graph, gtsam.symbol("x", kf_id), point_index[level].astype(np.float64),
                np.ascontiguousarray(keypoint_xy[level].T), noise_by_sigma[sigma], calibration,
            )  # fmt: skip
    _add_gauge(graph, poses, keyframe_ids, point_index)

    before = _reprojection_errors(poses, positions, keyframe_ids, keypoint_xy, point_index, camera)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.iterations)
    params.setRelativeErrorTol(config.relative_error_tolerance)
    ordering = gtsam.Ordering()
    for index in used.tolist():  # points first: the Schur complement
        ordering.push_back(index)
    for kf_id in poses:
        ordering.push_back(gtsam.symbol("x", kf_id))
    params.setOrdering(ordering)
    # Damping scaled by the Hessian's diagonal (Marquardt's): with GTSAM's default, identity-scaled
    # damping the first step on a many-keyframe map can put points behind cameras (infinite cost)
    # however large lambda grows (measured on a 110-keyframe synthetic map: no step accepted).
    params.setDiagonalDamping(True)
    try:
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    except RuntimeError as exc:  # e.g. an indeterminant system: the pose graph's answer stands
        log.warning("global bundle adjustment failed (%s); keeping the pose graph's estimates", exc)
        return None
    if graph.error(result) >= graph.error(values):
        log.warning("global bundle adjustment found no better map; keeping the pose graph's estimates")
        return None

    adjusted_points = np.full((len(point_keys), 3), np.nan)
    for index in used.tolist():
        adjusted_points[index] = result.atPoint3(index)
    adjusted_poses = {k: result.atPose3(gtsam.symbol("x", k)).matrix() for k in poses}
    after = _reprojection_errors(
        adjusted_poses, adjusted_points, keyframe_ids, keypoint_xy, point_index, camera
    )
    adjusted = dict(estimates)
    for kf_id, pose in adjusted_poses.items():
        scale = _scale(by_id[kf_id].points3d, observed.own_rows[kf_id], pose, adjusted_points)
        if scale is not None:
            sim3 = pose.copy()
            sim3[:3, :3] *= scale
            adjusted[kf_id] = sim3
    stats = GlobalBundleAdjustmentStats(
        len(poses), len(used), len(point_index), observed.loop_observations,
        float(np.median(before)), float(np.median(after)),
    )  # fmt: skip
    return AdjustedMap(adjusted, point_keys, adjusted_points, stats)


def repose_frame(
    adjusted: AdjustedMap,
    segment: int,
    observations: PointObservations,
    initial: np.ndarray,
    camera: pycolmap.Camera,
    config: GlobalBundleAdjustmentConfig,
) -> np.ndarray | None:
    """Camera-to-world SE(3) of a frame from its observations of the adjusted points, refined from
    ``initial`` (its pose through the adjusted keyframes); None when fewer than
    ``frame_min_inliers`` observations fit within ``frame_max_error_px``. The observations were
    inliers of the frame's own tracking, so pycolmap's robust refinement (Cauchy loss) from a close
    start needs no RANSAC: the observations within ``frame_search_factor`` x the threshold of the
    start are refined, then those within the threshold of the result."""
    points = adjusted.positions(segment, observations.point_ids)
    known = np.isfinite(points).all(axis=1)
    if known.sum() < config.frame_min_inliers:
        return None
    points = points[known]
    keypoints = np.asarray(observations.keypoints, np.float64)[known]
    cam_from_world = pycolmap.Rigid3d(np.linalg.inv(initial)[:3, :])
    options = pycolmap.AbsolutePoseRefinementOptions()
    threshold = config.frame_search_factor * config.frame_max_error_px
    for _ in range(2):
        fits = _pixel_errors(cam_from_world, points, keypoints, camera) < threshold
        if fits.sum() < config.frame_min_inliers:
            return None
        result = pycolmap.refine_absolute_pose(cam_from_world, keypoints, points, fits, camera, options)
        if result is None:
            return None
        cam_from_world = result["cam_from_world"]
        threshold = config.frame_max_error_px
    fits = _pixel_errors(cam_from_world, points, keypoints, camera) < threshold
    if fits.sum() < config.frame_min_inliers:
        return None
    matrix = np.eye(4)
    matrix[:3, :] = np.asarray(cam_from_world.matrix(), dtype=np.float64)
    return np.linalg.inv(matrix)


def _pixel_errors(
    cam_from_world: pycolmap.Rigid3d, points: np.ndarray, keypoints: np.ndarray, camera: pycolmap.Camera
) -> np.ndarray:
    matrix = np.asarray(cam_from_world.matrix(), dtype=np.float64)
    in_camera = points @ matrix[:, :3].T + matrix[:, 3]
    in_front = in_camera[:, 2] > 1e-9
    errors = np.full(len(points), np.inf)
    errors[in_front] = np.linalg.norm(camera.img_from_cam(in_camera[in_front]) - keypoints[in_front], axis=1)
    return errors


@dataclass(frozen=True)
class _Observations:
    """Every (keyframe, undistorted keypoint, point) triple; points are rows of ``keys``."""

    keyframe_ids: np.ndarray
    xy: np.ndarray
    point_index: np.ndarray
    #: Row of each (segment, point id).
    keys: dict[tuple[int, int], int]
    #: Per keyframe, the row of each of its keypoints' own point (-1 where none).
    own_rows: dict[int, np.ndarray]
    loop_observations: int
    #: Relative position noise of each keypoint (the observer's ``keypoint_sigmas``, else 1).
    sigma: np.ndarray


def _collect_observations(
    keyframes: Mapping[int, Keyframe], loops: Sequence[LoopCorrespondences], camera: CameraIntrinsics
) -> _Observations | None:
    keys: dict[tuple[int, int], int] = {}
    rows_kf: list[np.ndarray] = []
    rows_xy: list[np.ndarray] = []
    rows_point: list[np.ndarray] = []
    rows_sigma: list[np.ndarray] = []

    def add(observer: Keyframe, keypoints: np.ndarray, rows: np.ndarray) -> int:
        mapped = rows >= 0
        count = int(mapped.sum())
        rows_kf.append(np.full(count, observer.id, np.int64))
        rows_xy.append(camera.undistort(observer.keypoints[keypoints[mapped]]))
        rows_point.append(rows[mapped])
        sigmas = observer.keypoint_sigmas
        rows_sigma.append(
            np.ones(count) if sigmas is None else np.asarray(sigmas, np.float64)[keypoints[mapped]]
        )
        return count

    own_rows = {}
    for kf in keyframes.values():
        assert kf.point_ids is not None
        own_rows[kf.id] = np.array(
            [keys.setdefault((kf.segment, i), len(keys)) if i >= 0 else -1 for i in kf.point_ids.tolist()],
            np.int64,
        )
        add(kf, np.arange(len(kf.point_ids)), own_rows[kf.id])
    loop_observations = 0
    for loop in loops:
        if loop.query not in keyframes or loop.match not in keyframes or len(loop.pairs) == 0:
            continue
        pairs = np.asarray(loop.pairs, np.int64)
        query, match = keyframes[loop.query], keyframes[loop.match]
        loop_observations += add(query, pairs[:, 0], own_rows[match.id][pairs[:, 1]])
        loop_observations += add(match, pairs[:, 1], own_rows[query.id][pairs[:, 0]])
    if not keys:
        return None
    return _Observations(
        np.concatenate(rows_kf), np.concatenate(rows_xy), np.concatenate(rows_point), keys, own_rows,
        loop_observations, np.concatenate(rows_sigma),
    )  # fmt: skip


def _initial_points(
    keyframes: Mapping[int, Keyframe], estimates: Mapping[int, np.ndarray], observed: _Observations
) -> np.ndarray:
    """World position of each point from its oldest observing keyframe (NaN when none has it)."""
    positions = np.full((len(observed.keys), 3), np.nan)
    for kf_id in sorted(keyframes, reverse=True):  # older keyframes overwrite newer ones
        points3d = keyframes[kf_id].points3d
        if points3d is None:
            continue
        rows = observed.own_rows[kf_id]
        mapped = np.flatnonzero(_with_point(rows, points3d))
        S = estimates[kf_id]
        positions[rows[mapped]] = points3d[mapped] @ S[:3, :3].T + S[:3, 3]
    return positions


def _with_point(rows: np.ndarray, points3d: np.ndarray) -> np.ndarray:
    """Keypoints with a map point and a finite position in the keyframe's camera frame."""
    return (rows >= 0) & np.isfinite(points3d).all(axis=1)


def _add_gauge(
    graph: gtsam.NonlinearFactorGraph,
    poses: Mapping[int, np.ndarray],
    keyframe_ids: np.ndarray,
    point_index: np.ndarray,
) -> None:
    """Per connected part of the map: the oldest keyframe fixed, its distance to the next kept."""
    ids = np.array(sorted(poses))
    row = np.searchsorted(ids, keyframe_ids)
    incidence = coo_matrix((np.ones(len(row)), (row, point_index)), shape=(len(ids), point_index.max() + 1))
    adjacency = (incidence @ incidence.T).tocsr()
    _, labels = connected_components(adjacency, directed=False)
    tight6 = gtsam.noiseModel.Isotropic.Sigma(6, _FIXED_SIGMA)
    tight1 = gtsam.noiseModel.Isotropic.Sigma(1, _FIXED_SIGMA)
    for label in np.unique(labels).tolist():
        members = ids[labels == label].tolist()
        first = members[0]
        graph.add(gtsam.PriorFactorPose3(gtsam.symbol("x", first), gtsam.Pose3(poses[first]), tight6))
        if len(members) > 1:
            second = members[1]
            distance = float(np.linalg.norm(poses[second][:3, 3] - poses[first][:3, 3]))
            graph.add(
                gtsam.RangeFactorPose3(gtsam.symbol("x", first), gtsam.symbol("x", second), distance, tight1)
            )


def _reprojection_errors(
    poses: Mapping[int, np.ndarray],
    points: np.ndarray,
    keyframe_ids: np.ndarray,
    xy: np.ndarray,
    point_index: np.ndarray,
    camera: CameraIntrinsics,
) -> np.ndarray:
    """Pixel error of every observation (undistorted pixels, camera-to-world poses)."""
    ids = np.array(sorted(poses))
    stacked = np.stack([poses[k] for k in ids.tolist()])
    which = np.searchsorted(ids, keyframe_ids)
    rotation, center = stacked[which, :3, :3], stacked[which, :3, 3]
    in_camera = np.einsum("nji,nj->ni", rotation, points[point_index] - center)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = in_camera[:, :2] / in_camera[:, 2:] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    return np.nan_to_num(np.linalg.norm(uv - xy, axis=1), nan=np.inf)


def _scale(
    points3d: np.ndarray | None, rows: np.ndarray, pose: np.ndarray, adjusted_points: np.ndarray
) -> float | None:
    """The factor from a keyframe's own units (its ``points3d``, at point ``rows``) to the adjusted map's."""
    if points3d is None:
        return None
    mapped = np.flatnonzero(_with_point(rows, points3d))
    adjusted = adjusted_points[rows[mapped]]
    found = np.isfinite(adjusted).all(axis=1)
    if found.sum() < 3:
        return None
    in_camera = (adjusted[found] - pose[:3, 3]) @ pose[:3, :3]
    own = points3d[mapped[found]]
    ratio = np.linalg.norm(in_camera, axis=1) / np.maximum(np.linalg.norm(own, axis=1), 1e-12)
    return float(np.median(ratio))
