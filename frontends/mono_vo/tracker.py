"""Frame tracking against the local map, and relocalisation against earlier keyframes.

Tracking (ORB-SLAM's motion model + local map tracking, folded into one pass):

1. Predict the pose with a constant velocity model.
2. Project the points of the last ``local_keyframes`` keyframes (with the experimental
   ``covisible_keyframes``, also those ``SegmentMap.link_covisible`` linked); match them to
   keypoints within ``search_radius`` px (Hamming limit, ratio test; ``features.match_in_radius``).
   Too few matches (a sudden motion) doubles the radius once. As in ORB-SLAM, a point is searched
   for only if the camera sees it within ``max_view_angle_deg`` of its mean viewing direction and
   within its scale-invariance distance range, only among keypoints within one pyramid level of the
   level its distance predicts, and the matches must agree on the keypoint rotation (orientation histogram).
   Without these rules, background points hidden behind a near object passing in front of them
   were still projected and matched to the object's (repetitive) texture, and PnP followed the
   occluder while reporting a normal inlier count.
3. PnP RANSAC (seeded USAC) on those matches, then Levenberg-Marquardt refinement of its inliers;
   and the predicted pose, refined the same way on the matches within the PnP threshold of it.
4. Project again from each pose with the narrow ``refine_radius``, which recovers the points the
   wide search missed or confused, and keep the matches whose reprojection error is within 2.45
   sigma of their pyramid level; the pose with more of them wins (RANSAC's on a tie), and its
   matches are the frame's observations (a keyframe's map points). Where the map is seen in a strip
   beside a near object, a minimal sample can put RANSAC in the wrong basin of a nearly flat cost
   (synthetic loop 2, frame 274: 2.5 deg off, after which tracking was lost within 20 frames); the
   motion model's pose is a second start, judged on its own matches like RANSAC's. Where the two
   poses project the matched points within ``SAME_POSE_PX`` of each other, only RANSAC's searches.
5. With a rotation prior (``rotation_prior_acceleration``), the winning pose is refined once
   more on its matches together with the prediction's orientation (``refine_with_rotation_prior``),
   and the matches that no longer fit it are dropped. A plain refinement on the final matches,
   without the prior, measured no better than none (15 synthetic scenes, odometry ATE geometric
   mean: 0.040 m as is, 0.043 with OpenCV's Levenberg-Marquardt, 0.065 with pycolmap's
   Cauchy-robust ``refine_absolute_pose``, which collapsed three maps).

Relocalisation matches the frame's descriptors against the map points of recent keyframes (newest
first), solves PnP RANSAC, and accepts a pose only if tracking the local map from it then finds
``min_inliers`` inliers that fix the camera centre well enough (``max_centre_sigma``): a pose is
never taken from a handful of descriptor matches, nor from points in a strip of the view.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import gtsam
import numpy as np
from scipy.spatial import cKDTree

from frontends.mono_vo.config import RelocalisationConfig, TrackingConfig
from frontends.mono_vo.features import Features, consistent_rotation, match_in_radius, octave_sigmas
from frontends.mono_vo.geometry import (
    fit_or_none,
    frame_seed,
    from_rvec,
    invert,
    project,
    projection_jacobian,
    relative_centre_sigma,
    transform,
    usac_params,
)
from frontends.mono_vo.map import SegmentMap
from frontends.orb import match_descriptors

#: Two pose hypotheses that project every matched point this close (px) gather the same matches:
#: the second search is skipped (figure8 0: 67 % of the frames, 88 % of them with identical
#: matches, 0.15 matches apart on average; docs/2026-12-07-frame-rate.md).
SAME_POSE_PX = 0.1


@dataclass(frozen=True)
class PoseEstimate:
    #: World-to-camera pose.
    T_cw: np.ndarray
    #: Inlier keypoints of the frame and the map points they see.
    keypoint_idx: np.ndarray
    point_ids: np.ndarray


class Tracker:
    def __init__(
        self,
        settings: TrackingConfig,
        relocalisation: RelocalisationConfig,
        K: np.ndarray,
        octave_sigma: np.ndarray,
        image_size: tuple[int, int],
        count_scale: float,
        seed: int,
    ) -> None:
        self.settings = settings
        self.relocalisation = relocalisation
        self.K = K
        self.octave_sigma = octave_sigma
        self.width, self.height = image_size
        self.min_inliers = max(15, round(settings.min_inliers * count_scale))
        self.min_reloc_pnp = max(10, round(relocalisation.min_pnp_inliers * count_scale))
        self.min_reloc_inliers = max(20, round(relocalisation.min_inliers * count_scale))
        self.seed = seed

    def track(
        self,
        segment_map: SegmentMap,
        features: Features,
        tree: cKDTree,
        T_predicted: np.ndarray,
        frame_index: int,
        rotation_prior_sigma: float = 0.0,
    ) -> PoseEstimate | None:
        """The frame's pose from the local map, starting from ``T_predicted``; with
        ``rotation_prior_sigma`` (rad) > 0 the final pose keeps the predicted orientation within
        that sigma (``refine_with_rotation_prior``)."""
        s = self.settings
        local_ids = segment_map.local_point_ids(s.local_keyframes)
        pairs = self.search_by_projection(
            segment_map, local_ids, features, tree, T_predicted, s.search_radius
        )
        if len(pairs[0]) < 2 * self.min_inliers:
            wider = self.search_by_projection(
                segment_map, local_ids, features, tree, T_predicted, 2 * s.search_radius
            )
            if len(wider[0]) > len(pairs[0]):
                pairs = wider
        keypoint_idx, point_ids = pairs
        least = self.min_inliers // 2
        hypotheses = [
            self._pnp_ransac(segment_map, features, keypoint_idx, point_ids, frame_index, least),
            self._refine_prediction(segment_map, features, keypoint_idx, point_ids, T_predicted, least),
        ]
        if hypotheses[0] is not None and hypotheses[1] is not None:
            positions = segment_map.points.positions[point_ids]
            uv_ransac, _ = project(self.K, hypotheses[0], positions)
            uv_predicted, _ = project(self.K, hypotheses[1], positions)
            if np.nanmax(np.abs(uv_ransac - uv_predicted), initial=0.0) < SAME_POSE_PX:
                hypotheses.pop()  # RANSAC's pose would gather the same matches and win the tie
        # Each pose gathers its own matches from the local map; the one with more wins (RANSAC's on
        # a tie). Scored on the wide search's matches instead, the prediction would be favoured by
        # the matches its own search window selected (measured: 4 more collapses in 10 runs).
        best: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        for T_cw in hypotheses:
            if T_cw is None:
                continue
            found = self._local_map_matches(segment_map, local_ids, features, tree, T_cw)
            if best is None or len(found[0]) > len(best[1]):
                best = (T_cw, *found)
        if best is None or len(best[1]) < self.min_inliers:
            return None
        if rotation_prior_sigma > 0:
            best = self._with_rotation_prior(segment_map, features, *best, T_predicted, rotation_prior_sigma)
        return self._counted(segment_map, local_ids, PoseEstimate(*best))

    def _with_rotation_prior(
        self,
        segment_map: SegmentMap,
        features: Features,
        T_cw: np.ndarray,
        keypoint_idx: np.ndarray,
        point_ids: np.ndarray,
        T_predicted: np.ndarray,
        sigma: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The pose refined with the rotation prior, and the matches that still fit it; the pose
        as it was if fewer than ``min_inliers`` do."""
        sigmas = octave_sigmas(self.octave_sigma, features.octaves[keypoint_idx])
        refined = refine_with_rotation_prior(
            self.K, T_cw, segment_map.points.positions[point_ids], features.points[keypoint_idx], sigmas,
            T_predicted, sigma,
        )  # fmt: skip
        fit = self.fits(segment_map, features, keypoint_idx, point_ids, refined)
        if fit.sum() < self.min_inliers:
            return T_cw, keypoint_idx, point_ids
        return refined, keypoint_idx[fit], point_ids[fit]

    def track_local_map(
        self,
        segment_map: SegmentMap,
        local_ids: np.ndarray,
        features: Features,
        tree: cKDTree,
        T_cw: np.ndarray,
    ) -> PoseEstimate | None:
        """Narrow projection search around the PnP pose ``T_cw``; keeps the matches that fit it."""
        keypoint_idx, point_ids = self._local_map_matches(segment_map, local_ids, features, tree, T_cw)
        if len(keypoint_idx) < 6:
            return None
        return self._counted(segment_map, local_ids, PoseEstimate(T_cw, keypoint_idx, point_ids))

    def _local_map_matches(
        self,
        segment_map: SegmentMap,
        local_ids: np.ndarray,
        features: Features,
        tree: cKDTree,
        T_cw: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        keypoint_idx, point_ids = self.search_by_projection(
            segment_map, local_ids, features, tree, T_cw, self.settings.refine_radius
        )
        inlier = self.fits(segment_map, features, keypoint_idx, point_ids, T_cw)
        return keypoint_idx[inlier], point_ids[inlier]

    def _counted(
        self, segment_map: SegmentMap, local_ids: np.ndarray, estimate: PoseEstimate
    ) -> PoseEstimate:
        """Count the frame in ORB-SLAM's visible/found statistics of the local points (culling)."""
        points = segment_map.points
        uv, depth = project(self.K, estimate.T_cw, points.positions[local_ids])
        points.visible[local_ids[self._in_image(uv, depth)]] += 1
        points.found[estimate.point_ids] += 1
        return estimate

    def centre_sigma(
        self, segment_map: SegmentMap, T_cw: np.ndarray, features: Features, keypoint_idx: np.ndarray,
        point_ids: np.ndarray,
    ) -> float:  # fmt: skip
        """``relative_centre_sigma`` of a pose (``T_cw``) from these keypoints and map points."""
        sigmas = octave_sigmas(self.octave_sigma, features.octaves[keypoint_idx])
        return relative_centre_sigma(self.K, T_cw, segment_map.points.positions[point_ids], sigmas)

    def relocalise(
        self,
        segment_map: SegmentMap,
        features: Features,
        tree: cKDTree,
        frame_index: int,
        max_centre_sigma: float,
    ) -> PoseEstimate | None:
        """The frame's pose from the first anchor keyframe (newest first) whose matches give a PnP
        pose that tracks the local map with ``min_inliers`` inliers fixing the camera centre to at
        most ``max_centre_sigma`` (``centre_sigma``)."""
        r = self.relocalisation
        keyframes = segment_map.keyframes
        for position in range(len(keyframes) - 1, max(-1, len(keyframes) - 1 - r.max_keyframes), -1):
            anchor = keyframes[position]
            ids = segment_map.live_ids(anchor)
            observed = np.flatnonzero(ids >= 0)
            frame_idx, anchor_idx = match_descriptors(
                features.descriptors,
                anchor.features.descriptors[observed],
                r.ratio,
                self.settings.max_hamming,
            )
            if len(frame_idx) < self.min_reloc_pnp:
                continue
            point_ids = ids[observed[anchor_idx]]
            T_cw = self._pnp_ransac(
                segment_map, features, frame_idx, point_ids, frame_index, self.min_reloc_pnp
            )
            if T_cw is None:
                continue
            nearby = keyframes[
                max(0, position - self.settings.local_keyframes // 2) : position
                + 1
                + self.settings.local_keyframes // 2
            ]
            local_ids = np.unique(np.concatenate([segment_map.live_ids(kf) for kf in nearby]))
            estimate = self.track_local_map(segment_map, local_ids[local_ids >= 0], features, tree, T_cw)
            if (
                estimate is not None
                and len(estimate.keypoint_idx) >= self.min_reloc_inliers
                and self.centre_sigma(
                    segment_map, estimate.T_cw, features, estimate.keypoint_idx, estimate.point_ids
                )
                <= max_centre_sigma
            ):
                return estimate
        return None

    def search_by_projection(
        self,
        segment_map: SegmentMap,
        local_ids: np.ndarray,
        features: Features,
        tree: cKDTree,
        T_cw: np.ndarray,
        radius: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Project ``local_ids`` from ``T_cw`` and match them to the keypoints within ``radius`` px
        (ORB-SLAM's checks, module docstring step 2): (keypoint indices, point ids)."""
        points = segment_map.points
        s = self.settings
        uv, depth = project(self.K, T_cw, points.positions[local_ids])
        ray = points.positions[local_ids] - invert(T_cw)[:3, 3]
        distance = np.maximum(np.linalg.norm(ray, axis=1), 1e-12)
        cosine = np.einsum("ij,ij->i", ray, points.normals[local_ids]) / distance
        searched = (
            self._in_image(uv, depth)
            & (cosine >= np.cos(np.radians(s.max_view_angle_deg)))
            & (distance >= points.min_distance[local_ids] / s.distance_margin)
            & (distance <= points.max_distance[local_ids] * s.distance_margin)
        )
        candidates = local_ids[searched]
        scale = segment_map.octave_scale
        level = np.ceil(np.log(points.max_distance[candidates] / distance[searched]) / np.log(scale[1]))
        point_idx, keypoint_idx = match_in_radius(
            uv[searched],
            points.descriptors[candidates],
            np.clip(level, 0, len(scale) - 1).astype(np.int64),
            tree,
            features,
            radius,
            s.max_hamming,
            s.ratio,
        )
        if s.rotation_bins > 0:
            consistent = consistent_rotation(
                features.angles[keypoint_idx] - points.angles[candidates[point_idx]],
                s.rotation_bins,
                s.rotation_min_share,
            )
            point_idx, keypoint_idx = point_idx[consistent], keypoint_idx[consistent]
        return keypoint_idx, candidates[point_idx]

    def _in_image(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            return (
                (depth > 0)
                & (uv[:, 0] >= 0)
                & (uv[:, 0] < self.width)
                & (uv[:, 1] >= 0)
                & (uv[:, 1] < self.height)
            )

    def _pnp_ransac(
        self,
        segment_map: SegmentMap,
        features: Features,
        keypoint_idx: np.ndarray,
        point_ids: np.ndarray,
        frame_index: int,
        min_inliers: int,
    ) -> np.ndarray | None:
        if len(keypoint_idx) < max(min_inliers, 6):
            return None
        object_points = segment_map.points.positions[point_ids]
        image_points = features.points[keypoint_idx]
        params = usac_params(
            frame_seed(self.seed, frame_index, 4),
            self.settings.pnp_threshold,
            thorough=False,
            max_iterations=200,
        )
        fitted = fit_or_none(cv2.solvePnPRansac, object_points, image_points, self.K, None, params=params)
        if fitted is None:
            return None
        ok, _, rvec, tvec, inliers = fitted
        if not ok or inliers is None or len(inliers) < min_inliers:
            return None
        inliers = inliers.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(
            object_points[inliers], image_points[inliers], self.K, None, rvec, tvec
        )
        return from_rvec(rvec, tvec)

    def _refine_prediction(
        self,
        segment_map: SegmentMap,
        features: Features,
        keypoint_idx: np.ndarray,
        point_ids: np.ndarray,
        T_predicted: np.ndarray,
        min_inliers: int,
    ) -> np.ndarray | None:
        """The predicted pose refined (Levenberg-Marquardt) on the matches within the PnP threshold
        of it; None with fewer than ``min_inliers`` of them."""
        object_points = segment_map.points.positions[point_ids]
        image_points = features.points[keypoint_idx]
        uv, depth = project(self.K, T_predicted, object_points)
        error = np.nan_to_num(np.linalg.norm(uv - image_points, axis=1), nan=np.inf)
        inliers = np.flatnonzero((depth > 0) & (error < self.settings.pnp_threshold))
        if len(inliers) < max(min_inliers, 6):
            return None
        rvec, tvec = cv2.solvePnPRefineLM(
            object_points[inliers], image_points[inliers], self.K, None,
            cv2.Rodrigues(T_predicted[:3, :3])[0], T_predicted[:3, 3].reshape(3, 1).copy(),
        )  # fmt: skip
        return from_rvec(rvec, tvec)

    def fits(
        self,
        segment_map: SegmentMap,
        features: Features,
        keypoint_idx: np.ndarray,
        point_ids: np.ndarray,
        T_cw: np.ndarray,
    ) -> np.ndarray:
        """Which matches reproject within ``inlier_threshold`` pyramid sigmas from ``T_cw``."""
        uv, depth = project(self.K, T_cw, segment_map.points.positions[point_ids])
        error = np.nan_to_num(np.linalg.norm(uv - features.points[keypoint_idx], axis=1), nan=np.inf)
        sigma = octave_sigmas(self.octave_sigma, features.octaves[keypoint_idx])
        return (depth > 0) & (error < self.settings.inlier_threshold * sigma)


def refine_with_rotation_prior(
    K: np.ndarray,
    T_cw: np.ndarray,
    points_w: np.ndarray,
    pixels: np.ndarray,
    sigmas: np.ndarray,
    T_predicted: np.ndarray,
    rotation_sigma: float,
) -> np.ndarray:
    """Pose-only refinement (GTSAM Levenberg-Marquardt, from ``T_cw``) of a camera seeing
    ``points_w`` at ``pixels`` (``sigmas`` px), with a prior that its orientation is
    ``T_predicted``'s within ``rotation_sigma`` (rad); the translation has no prior.

    Where the map is seen in a narrow strip of the view (a near, textureless object hides the
    rest), the pixels fix a combination of rotation and sideways translation but not each: the
    cost is a long valley and noise picks a point along it. On synthetic out-and-back 1, PnP
    poses wandered 0.3-1.2 deg from the true per-frame turn of 0.06 deg, the translation took up
    the rest and the map's scale fell ~7 % per keyframe. The constant-velocity prediction's
    orientation is the missing constraint. Where the pixels fix the pose (synthetic loop 0: the
    tracked points' rotation sigma is 0.03-0.08 deg, 10th-90th percentile) a prior of 0.3 deg
    moves it by about (0.05 / 0.3)^2 of the prediction's difference."""
    T_wc_key = gtsam.symbol("x", 0)
    observed = pixels.astype(np.float64).ravel()

    def reprojection(factor: gtsam.CustomFactor, values: gtsam.Values, jacobians: list | None) -> np.ndarray:
        T_wc = values.atPose3(T_wc_key).matrix()
        # Not ``project``: the Jacobian needs the camera-frame points, and NaN would stall LM.
        camera = transform(invert(T_wc), points_w)
        uv = camera[:, :2] / camera[:, 2:3] * K[[0, 1], [0, 1]] + K[:2, 2]
        if jacobians is not None:
            # GTSAM perturbs T_wc on the right (camera frame): dX = -(w x X) - v.
            jacobians[0] = -projection_jacobian(K, camera).reshape(-1, 6)
        return uv.ravel() - observed

    graph = gtsam.NonlinearFactorGraph()
    pixel_noise = gtsam.noiseModel.Diagonal.Sigmas(np.repeat(sigmas, 2))
    graph.add(gtsam.CustomFactor(pixel_noise, [T_wc_key], reprojection))
    predicted_orientation = gtsam.Rot3(T_predicted[:3, :3].T)
    graph.add(
        gtsam.PoseRotationPrior3D(
            T_wc_key, predicted_orientation, gtsam.noiseModel.Isotropic.Sigma(3, rotation_sigma)
        )
    )
    values = gtsam.Values()
    values.insert(T_wc_key, gtsam.Pose3(invert(T_cw)))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(10)
    params.setRelativeErrorTol(1e-6)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return invert(result.atPose3(T_wc_key).matrix())
