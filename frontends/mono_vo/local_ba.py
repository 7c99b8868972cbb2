"""Local bundle adjustment with GTSAM after every new keyframe.

Variables: the poses of the last ``window`` keyframes and every map point they observe. Keyframes
outside the window that also observe those points enter as fixed cameras, like ORB-SLAM's
local BA, which anchors the window to the older map: position, orientation and scale of the map
stay where the earlier keyframes put them. At the start of a segment there are no older keyframes;
then the first keyframe is fixed and the second keeps only its distance from the first (a range
factor): that fixes the gauge's seventh degree of freedom, the map's scale, and nothing more. The
direction of the first baseline stays free, so later keyframes can correct an initialisation whose
translation was poorly conditioned (a short baseline during a rotation). With
``start_orientation_prior`` (the default) the second keyframe also keeps its orientation (see its
setting). When the window first slides past the start, a single older keyframe anchors it, which
leaves the window's scale free: the oldest window keyframe then keeps its distance from that anchor.

Factors are ``GenericProjectionFactorCal3_S2`` on undistorted pixels (points keyed by their id)
with a Huber kernel; the pixel sigma grows with the keypoint's pyramid level. Levenberg-Marquardt
eliminates the points before the poses (the Schur complement) and runs until an iteration gains
less than ``relative_error_tolerance`` (at most ``iterations``). Afterwards observations whose
reprojection error exceeds ``huber_k`` sigmas (chi2 95 % with 2 dof) or that fell behind the camera
are removed from the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from frontends.mono_vo.config import BundleAdjustmentConfig
from frontends.mono_vo.features import octave_sigmas
from frontends.mono_vo.geometry import invert, project
from frontends.mono_vo.map import KeyframeState, SegmentMap

_FIXED_SIGMA = 1e-6
#: Sigma of a prior's unconstrained components (map units): no pull at the map's scale.
_FREE_SIGMA = 1e3


@dataclass(frozen=True)
class BundleAdjustmentStats:
    keyframes: int
    points: int
    observations: int
    outliers: int
    #: Median reprojection error (px) after the optimisation.
    median_error_px: float


def local_bundle_adjustment(
    segment_map: SegmentMap, K: np.ndarray, octave_sigma: np.ndarray, settings: BundleAdjustmentConfig
) -> BundleAdjustmentStats | None:
    keyframes = segment_map.keyframes
    window = keyframes[-settings.window :]
    point_ids = np.unique(np.concatenate([segment_map.live_ids(kf) for kf in window]))
    point_ids = point_ids[point_ids >= 0]
    if len(point_ids) == 0:
        return None
    fixed = _anchoring_keyframes(segment_map, len(window), point_ids, settings.max_fixed)
    observations = _observations(segment_map, [*window, *fixed], point_ids)

    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    calibration = gtsam.Cal3_S2(K[0, 0], K[1, 1], 0.0, K[0, 2], K[1, 2])
    noise_by_octave = [
        gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(settings.huber_k),
            gtsam.noiseModel.Isotropic.Sigma(2, sigma),
        )
        for sigma in octave_sigma
    ]
    # With two or more anchors, the anchors are cameras, not variables: the same solution as
    # variables held by tight priors, at ~30 % less solve time (docs/2026-12-07-frame-rate.md).
    # One anchor stays a variable: the range factor that holds the scale needs its key.
    fixed_cameras = len(fixed) >= 2
    variables = window if fixed_cameras else [*window, *fixed]
    for kf in variables:
        values.insert(gtsam.symbol("x", kf.id), gtsam.Pose3(invert(kf.T_cw)))
    positions = segment_map.points.positions
    # Points are keyed by their id (pose keys are symbols, far above any id), which lets GTSAM's
    # batch insertProjectionFactors build each keyframe's factors per pyramid level in C++: the
    # same factors as one constructor call per observation, at half the cost.
    for pid in point_ids.tolist():
        values.insert(pid, positions[pid])
    for position, (kf, keypoint_idx, ids) in enumerate(observations):
        pose_key = gtsam.symbol("x", kf.id)
        octaves = np.minimum(kf.features.octaves[keypoint_idx], len(noise_by_octave) - 1)
        if fixed_cameras and position >= len(window):
            camera = gtsam.PinholeCameraCal3_S2(gtsam.Pose3(invert(kf.T_cw)), calibration)
            measured = kf.features.points[keypoint_idx]
            for pid, uv, octave in zip(ids.tolist(), measured, octaves.tolist(), strict=True):
                graph.add(gtsam.TriangulationFactorCal3_S2(camera, uv, noise_by_octave[octave], pid))
            continue
        for octave in np.unique(octaves).tolist():
            chosen = octaves == octave
            gtsam.utilities.insertProjectionFactors(
                graph, pose_key, ids[chosen].astype(np.float64),
                np.ascontiguousarray(kf.features.points[keypoint_idx[chosen]].T), noise_by_octave[octave],
                calibration,
            )  # fmt: skip
    held = [] if fixed_cameras else fixed
    _add_gauge_priors(graph, window, held, settings.start_orientation_prior, bool(fixed))

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(settings.iterations)
    params.setRelativeErrorTol(settings.relative_error_tolerance)
    params.setOrdering(_points_first_ordering(point_ids, variables))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()

    for kf in window:
        kf.T_cw = invert(result.atPose3(gtsam.symbol("x", kf.id)).matrix())
    for pid in point_ids.tolist():
        positions[pid] = result.atPoint3(pid)
    outliers, errors = _remove_outliers(segment_map, K, octave_sigma, observations, settings.huber_k)
    return BundleAdjustmentStats(
        len(window), len(point_ids), sum(len(o[1]) for o in observations), outliers,
        float(np.median(errors)) if len(errors) else 0.0,
    )  # fmt: skip


def _points_first_ordering(point_ids: np.ndarray, keyframes: list[KeyframeState]) -> gtsam.Ordering:
    """Eliminate every point before any pose: each point depends only on the poses that see it,
    so this is the Schur complement of bundle adjustment. GTSAM's ColamdConstrainedLast gives the
    same solve time but costs ~4 ms more per call to compute; plain COLAMD solves ~7 % slower."""
    ordering = gtsam.Ordering()
    for pid in point_ids.tolist():
        ordering.push_back(pid)
    for kf in keyframes:
        ordering.push_back(gtsam.symbol("x", kf.id))
    return ordering


def _anchoring_keyframes(
    segment_map: SegmentMap, window_size: int, point_ids: np.ndarray, max_fixed: int
) -> list[KeyframeState]:
    """The most recent keyframes before the window that observe any of the window's points."""
    fixed = []
    for kf in reversed(segment_map.keyframes[:-window_size]):
        if np.isin(segment_map.live_ids(kf), point_ids).any():
            fixed.append(kf)
            if len(fixed) == max_fixed:
                break
    return fixed


def _observations(
    segment_map: SegmentMap, keyframes: list[KeyframeState], point_ids: np.ndarray
) -> list[tuple[KeyframeState, np.ndarray, np.ndarray]]:
    """Per keyframe: indices of its keypoints that observe ``point_ids``, and those point ids."""
    result = []
    for kf in keyframes:
        ids = segment_map.live_ids(kf)
        keypoint_idx = np.flatnonzero(np.isin(ids, point_ids))
        result.append((kf, keypoint_idx, ids[keypoint_idx]))
    return result


def _add_gauge_priors(
    graph: gtsam.NonlinearFactorGraph,
    window: list[KeyframeState],
    fixed: list[KeyframeState],
    start_orientation_prior: bool,
    anchored: bool,
) -> None:
    """Priors that fix the gauge: on the anchors in ``fixed`` (variables held by priors), or, when
    not ``anchored`` (a segment's start), on the window's first two keyframes."""
    tight = gtsam.noiseModel.Isotropic.Sigma(6, _FIXED_SIGMA)
    for kf in fixed:
        graph.add(gtsam.PriorFactorPose3(gtsam.symbol("x", kf.id), gtsam.Pose3(invert(kf.T_cw)), tight))
    if len(fixed) == 1:
        # One anchor fixes six of the Sim(3) gauge's seven degrees of freedom: hold the scale too.
        # Without it the first BA after the start could rescale the window at once (320x240 loop,
        # start orientation held: the map shrank 5x in one keyframe step in 3 of 10 seeds).
        _add_range(graph, fixed[0], window[0])
    if anchored:
        return
    # Segment start: fix the first keyframe and the distance (the map's scale) of the second; the
    # direction of the first baseline stays free.
    first, *rest = window
    graph.add(gtsam.PriorFactorPose3(gtsam.symbol("x", first.id), gtsam.Pose3(invert(first.T_cw)), tight))
    if rest:
        second = rest[0]
        _add_range(graph, first, second)
        if start_orientation_prior:
            # Pose3 tangent order is (rotation, translation): a fixed rotation, a free translation.
            sigmas = np.array([_FIXED_SIGMA] * 3 + [_FREE_SIGMA] * 3)
            orientation_only = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
            second_key = gtsam.symbol("x", second.id)
            graph.add(gtsam.PriorFactorPose3(second_key, gtsam.Pose3(invert(second.T_cw)), orientation_only))


def _add_range(graph: gtsam.NonlinearFactorGraph, anchor: KeyframeState, kf: KeyframeState) -> None:
    """Hold ``kf``'s current distance from ``anchor`` (the map's scale)."""
    distance = float(np.linalg.norm(invert(kf.T_cw)[:3, 3] - invert(anchor.T_cw)[:3, 3]))
    noise = gtsam.noiseModel.Isotropic.Sigma(1, _FIXED_SIGMA)
    graph.add(gtsam.RangeFactorPose3(gtsam.symbol("x", anchor.id), gtsam.symbol("x", kf.id), distance, noise))


def _remove_outliers(
    segment_map: SegmentMap,
    K: np.ndarray,
    octave_sigma: np.ndarray,
    observations: list[tuple[KeyframeState, np.ndarray, np.ndarray]],
    huber_k: float,
) -> tuple[int, np.ndarray]:
    removed = 0
    errors = []
    for kf, keypoint_idx, ids in observations:
        uv, depth = project(K, kf.T_cw, segment_map.points.positions[ids])
        error = np.nan_to_num(np.linalg.norm(uv - kf.features.points[keypoint_idx], axis=1), nan=np.inf)
        sigma = octave_sigmas(octave_sigma, kf.features.octaves[keypoint_idx])
        bad = (depth <= 0) | (error > huber_k * sigma)
        segment_map.drop_observations(kf, keypoint_idx[bad])
        removed += int(bad.sum())
        errors.append(error[~bad])
    return removed, np.concatenate(errors) if errors else np.zeros(0)
