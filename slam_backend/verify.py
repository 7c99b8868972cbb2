"""Geometric verification of loop candidates: does keyframe ``query`` really see ``match``'s place?

A verifier turns a candidate pair of keyframes into a relative Sim(3) loop constraint with a
covariance, or a rejection with its reason. The ``pycolmap`` verifier (default):

1. ORB matching: Hamming nearest neighbours with Lowe's ratio test and a mutual check (OpenCV).
2. Two-view geometry with LO-RANSAC (``pycolmap.estimate_calibrated_two_view_geometry``): the
   matches must fit one epipolar geometry (``min_inliers``, ``min_inlier_ratio``).
3. The relative Sim(3) from the map points of the epipolar inliers: both keyframes carry the 3D
   point of each keypoint in their own camera frame (``Keyframe.points3d``), and
   ``pycolmap.estimate_sim3d_robust`` aligns the query's points onto the match's
   (``max_point_error``). As ORB-SLAM checks its Sim(3), the points are judged by reprojection:
   a point fits when, mapped through the Sim(3), it lands within ``max_reprojection_error_px`` of
   its keypoint in the other image, both ways (``min_points``, ``min_point_inlier_ratio``). Two
   visits of a place on a drifted map agree in the images while their depths differ by more than
   any 3D threshold would allow (docs/2026-12-07-sim3-reprojection.md).
4. The rotation and translation are refined, with their covariance, by PnP of the query's
   keypoints against the match's points (``pycolmap.estimate_and_refine_absolute_pose``).
5. The whole scene must agree, not only the matched points (ORB-SLAM's search by projection after
   its Sim(3)): of the match's map points that the constraint puts in the query's view, at least
   ``min_scene_share`` find a query keypoint within ``max_reprojection_error_px`` whose descriptor
   is within ``max_hamming``. Two instances of one object model (the same texture) give 30-35
   epipolar inliers that fit one rigid motion, 90 deg off; their scene around them does not
   follow (shares 0.12-0.20 against >= 0.47 for right loops; docs/2026-12-07-aliased-loops.md).

The constraint is ``relative = match_from_query`` as a 4x4 ``[s R, t; 0, 1]`` (a query-camera point
X maps to s R X + t in the match camera), which is what ``PoseGraphBackend.add_loop(match, query,
relative, covariance)`` expects (``pose(match)^-1 * pose(query)``). Covariance: 7x7 in
``slam_backend.lie``'s Sim(3) order; rotation and translation blocks from the PnP covariance, made
isotropic (their mean variance per axis, which is invariant to the frame change between the PnP
pose and ``relative``), the translation's no smaller than the two maps' disagreement (the median
squared 3D residual of the fitting points, per axis), log-scale variance from the spread of the
per-point distance ratios.

Keyframes without map points (e.g. from the ``replay`` frontend) cannot give a scale: such pairs
are rejected with that reason. Every random choice takes ``seed``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from frontends.config import load_config
from frontends.errors import ConfigError
from frontends.mono_vo.masking import inside
from frontends.orb import hamming, match_descriptors
from frontends.types import CameraIntrinsics, Keyframe
from lcd.objects.filtering import WALKING_LABELS
from slam_backend import plugins


@dataclass(frozen=True)
class Verification:
    """The outcome for one candidate; ``relative``/``covariance`` are set when ``verified``."""

    query: int
    match: int
    verified: bool
    #: Why it was rejected ("" when verified), e.g. "12 epipolar inliers < 30".
    reason: str
    matches: int = 0
    inliers: int = 0
    relative: np.ndarray | None = None
    covariance: np.ndarray | None = None
    #: (M, 2) keypoint indices (query, match) of the pairs the constraint rests on (PnP inliers).
    correspondences: np.ndarray | None = None
    #: The images agree (the two-view stage passed) but too few epipolar inliers have a map point in
    #: both keyframes: the map is thin there, the place may well be right (``LoopClosing`` defers it).
    thin_map: bool = False
    #: The two-view stage's result when ``thin_map`` (what ``LoopClosing`` can join segments with).
    two_view: TwoViewVerification | None = field(default=None, repr=False, compare=False)
    #: The images agree and enough epipolar inliers have map points in both keyframes, but too few
    #: of those fit one Sim(3): mostly a revisit on maps that drifted apart there.
    maps_disagree: bool = False

    @property
    def scale(self) -> float:
        return (
            float(np.cbrt(np.linalg.det(self.relative[:3, :3])))
            if self.relative is not None
            else float("nan")
        )


class Verifier(Protocol):
    name: str

    def verify(self, query: Keyframe, match: Keyframe) -> Verification: ...


class VerifierFactory(Protocol):
    def __call__(
        self, camera: CameraIntrinsics, overrides: Sequence[str] = (), config_path: Any = None
    ) -> Verifier: ...


# Defined where listing names needs no pycolmap; re-exported here.
VERIFIERS = plugins.VERIFIERS


@dataclass(frozen=True)
class VerifierConfig:
    #: Lowe's ratio: best Hamming distance below this times the second best.
    ratio: float = 0.8
    #: Matches farther than this many bits are never kept (ORB: 256 bits).
    max_hamming: int = 80
    #: Epipolar RANSAC threshold in pixels.
    max_epipolar_error_px: float = 4.0
    #: Descriptor matches needed to attempt the epipolar geometry.
    min_matches: int = 30
    #: Epipolar RANSAC inliers needed.
    min_inliers: int = 30
    #: Share of the matches that must be epipolar inliers.
    min_inlier_ratio: float = 0.25
    #: Epipolar inliers with map points in both keyframes for the Sim(3) (docs/2026-12-06-config-evidence.md)
    min_points: int = 30
    #: Sim(3) RANSAC threshold (fraction of the median point depth) (docs/2026-12-06-config-evidence.md)
    max_point_error: float = 0.03
    #: Share of the shared map points that the Sim(3) maps within max_reprojection_error_px, both ways
    min_point_inlier_ratio: float = 0.7
    #: PnP RANSAC threshold, and the Sim(3)'s reprojection threshold in both images (pixels).
    max_reprojection_error_px: float = 4.0
    #: Share of the match's map points put in the query's view that find a keypoint there (step 5 above)
    min_scene_share: float = 0.3
    #: Floor of the constraint's rotation sigma (rad): the estimates' spread ignores systematic errors.
    min_rotation_sigma_rad: float = 0.003
    #: Floor of the constraint's translation sigma (fraction of the match's median point depth).
    min_translation_sigma: float = 0.01
    #: Floor of the log-scale's standard deviation.
    min_log_scale_sigma: float = 0.02
    #: Keypoints in detected boxes of these classes are not matched (they move between visits).
    ignore_labels: tuple[str, ...] = WALKING_LABELS
    #: Two-view pose of a planar fit too (homography decomposition), not only an essential matrix's.
    planar_pose: bool = False
    #: Seed of pycolmap's RANSAC.
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0 < self.ratio <= 1:
            raise ConfigError(f"verifier: ratio must be in (0, 1], got {self.ratio}")
        if min(self.min_matches, self.min_inliers, self.min_points) < 5:
            raise ConfigError("verifier: min_matches, min_inliers and min_points must be >= 5")
        if not 0 <= self.min_inlier_ratio <= 1 or not 0 <= self.min_point_inlier_ratio <= 1:
            raise ConfigError("verifier: inlier ratios must be in [0, 1]")
        if not 0 <= self.min_scene_share <= 1:
            raise ConfigError("verifier: min_scene_share must be in [0, 1]")


def colmap_camera(camera: CameraIntrinsics) -> pycolmap.Camera:
    if camera.is_distorted:
        d = camera.dist_coeffs
        return pycolmap.Camera(
            model="OPENCV",
            width=camera.width,
            height=camera.height,
            params=[camera.fx, camera.fy, camera.cx, camera.cy, d[0], d[1], d[2], d[3]],
        )
    return pycolmap.Camera(
        model="PINHOLE",
        width=camera.width,
        height=camera.height,
        params=[camera.fx, camera.fy, camera.cx, camera.cy],
    )


@dataclass(frozen=True)
class TwoViewVerification:
    """Stages 1-2 of the verification (ORB matching, epipolar geometry): images only, no map."""

    #: Enough matches and epipolar inliers (``min_matches``, ``min_inliers``, ``min_inlier_ratio``).
    passed: bool
    #: Why it failed ("" when it passed).
    reason: str
    matches: int
    #: (K, 2) keypoint indices (query, match) of the epipolar inliers; empty when matching failed.
    inlier_pairs: np.ndarray
    #: ``match_from_query`` [R | t] (3x4, |t| = 1) from the essential matrix when it passed and the
    #: geometry is a calibrated two-view one (None for planar, panoramic or uncalibrated fits).
    match_from_query: np.ndarray | None = None
    #: Median triangulation angle of the inliers (deg) under that pose; 0 without one.
    triangulation_angle_deg: float = 0.0

    @property
    def inliers(self) -> int:
        return len(self.inlier_pairs)


def verify_two_view(
    query: Keyframe, match: Keyframe, camera: pycolmap.Camera, config: VerifierConfig
) -> TwoViewVerification:
    """Does ``query`` see ``match``'s place by its image alone? The first two stages of
    ``PycolmapVerifier.verify`` (which calls this), also used by ``symbio eval lcd --verify``."""
    # A person who walked through both views gives matches that agree with one rigid motion, the
    # person's, not the camera's (docs/2026-12-06-walking-people.md).
    in_query, in_match = (_unmasked(k, config.ignore_labels) for k in (query, match))
    found_query, found_match = match_descriptors(
        query.descriptors[in_query],
        match.descriptors[in_match],
        config.ratio,
        config.max_hamming,
        mutual=True,
    )
    pairs = np.stack((in_query[found_query], in_match[found_match]), axis=1)
    if len(pairs) < config.min_matches:
        reason = f"{len(pairs)} descriptor matches < {config.min_matches}"
        return TwoViewVerification(False, reason, len(pairs), np.zeros((0, 2), dtype=np.int64))
    options = pycolmap.TwoViewGeometryOptions()
    options.ransac.max_error = config.max_epipolar_error_px
    options.ransac.random_seed = config.seed
    options.compute_relative_pose = True
    geometry = pycolmap.estimate_calibrated_two_view_geometry(
        camera,
        query.keypoints.astype(np.float64),
        camera,
        match.keypoints.astype(np.float64),
        pairs.astype(np.uint32),
        options,
    )
    inliers = np.asarray(geometry.inlier_matches, dtype=np.int64).reshape(-1, 2)
    if len(inliers) < config.min_inliers or len(inliers) / len(pairs) < config.min_inlier_ratio:
        reason = (
            f"{len(inliers)} epipolar inliers of {len(pairs)} matches "
            f"(need {config.min_inliers} and ratio {config.min_inlier_ratio})"
        )
        return TwoViewVerification(False, reason, len(pairs), inliers)
    relative = geometry.cam2_from_cam1
    posed = {pycolmap.TwoViewGeometryConfiguration.CALIBRATED}
    if config.planar_pose:
        posed.add(pycolmap.TwoViewGeometryConfiguration.PLANAR)
    if geometry.config not in posed or relative is None:
        return TwoViewVerification(True, "", len(pairs), inliers)
    pose = np.asarray(relative.matrix(), dtype=np.float64)
    return TwoViewVerification(True, "", len(pairs), inliers, pose, float(np.degrees(geometry.tri_angle)))


def _unmasked(keyframe: Keyframe, labels: Sequence[str]) -> np.ndarray:
    """Indices of the keyframe's keypoints outside the boxes of its objects of class ``labels``."""
    keypoints = np.asarray(keyframe.keypoints).reshape(-1, 2)
    keep = np.ones(len(keypoints), dtype=bool)
    for obj in getattr(keyframe, "objects", ()):
        if obj.label in labels:
            keep &= ~inside(keypoints, obj.box)
    return np.flatnonzero(keep)


class PycolmapVerifier:
    """See the module docstring."""

    name = "pycolmap"

    def __init__(self, camera: CameraIntrinsics, config: VerifierConfig = VerifierConfig()) -> None:
        self.config = config
        self.camera = colmap_camera(camera)

    def verify(self, query: Keyframe, match: Keyframe) -> Verification:
        config = self.config
        ids = (query.id, match.id)
        two_view = verify_two_view(query, match, self.camera, config)
        if not two_view.passed:
            return Verification(*ids, False, two_view.reason, two_view.matches, two_view.inliers)
        inliers, matches = two_view.inlier_pairs, two_view.matches
        if query.points3d is None or match.points3d is None:
            return Verification(
                *ids, False, "no map points: the relative scale is unobservable", matches, len(inliers)
            )
        both = inliers[
            np.isfinite(query.points3d[inliers[:, 0]]).all(axis=1)
            & np.isfinite(match.points3d[inliers[:, 1]]).all(axis=1)
        ]
        if len(both) < config.min_points:
            return Verification(
                *ids,
                False,
                f"{len(both)} inliers with map points < {config.min_points}",
                matches,
                len(inliers),
                thin_map=True,
                two_view=two_view,
            )
        return self._sim3(query, match, both, matches, len(inliers))

    def _sim3(
        self, query: Keyframe, match: Keyframe, both: np.ndarray, matches: int, inliers: int
    ) -> Verification:
        config = self.config
        ids = (query.id, match.id)
        assert query.points3d is not None and match.points3d is not None
        source = query.points3d[both[:, 0]].astype(np.float64)
        target = match.points3d[both[:, 1]].astype(np.float64)
        depth = float(np.median(np.linalg.norm(target, axis=1)))
        options = pycolmap.RANSACOptions()
        options.max_error = config.max_point_error * depth
        options.random_seed = config.seed
        # pycolmap 3.x returns a dict (tgt_from_src, num_inliers, inlier_mask); its stub says Sim3d.
        estimate: Any = pycolmap.estimate_sim3d_robust(source, target, options)
        fitted = np.asarray(estimate["inlier_mask"], dtype=bool) if estimate is not None else None
        # pycolmap returns the best minimal sample's model, unrefined (on a pair with exact depths:
        # 2 % off in scale, 4 px median reprojection error); least squares over its inliers is not.
        transform = (
            pycolmap.estimate_sim3d(source[fitted], target[fitted])
            if fitted is not None and fitted.sum() >= 3
            else None
        )
        if transform is None:
            return Verification(*ids, False, "no Sim(3) fits the map points", matches, inliers)
        matrix = np.asarray(transform.matrix(), dtype=np.float64)
        good = self._reprojected(
            matrix, source, target, query.keypoints[both[:, 0]], match.keypoints[both[:, 1]]
        )
        if good.mean() < config.min_point_inlier_ratio or good.sum() < config.min_points:
            return Verification(
                *ids,
                False,
                f"{int(good.sum())} of {len(good)} map points reproject through the Sim(3) within "
                f"{config.max_reprojection_error_px} px both ways "
                f"(need {config.min_points} and ratio {config.min_point_inlier_ratio})",
                matches,
                inliers,
                maps_disagree=True,
            )
        scale = float(transform.scale)
        pnp = self._pnp(query, target[good], both[good, 0])
        if pnp is None:
            return Verification(
                *ids, False, "PnP of the query against the match's points failed", matches, inliers
            )
        match_from_query, pose_covariance, pnp_inliers = pnp
        relative = np.eye(4)
        relative[:3, :3] = scale * match_from_query[:3, :3]
        relative[:3, 3] = match_from_query[:3, 3]
        found, in_view = self._scene_agreement(query, match, relative)
        if found < config.min_scene_share * in_view:
            return Verification(
                *ids,
                False,
                f"{found} of the match's {in_view} map points in the query's view find a keypoint there "
                f"(need share {config.min_scene_share}): only the matched part of the scene agrees",
                matches,
                inliers,
            )
        # Two maps of a place that disagree in depth (a drifted revisit) give a translation no better
        # than their disagreement: the median squared 3D residual, per axis
        # (docs/2026-12-07-sim3-reprojection.md).
        moved = source[good] @ matrix[:, :3].T + matrix[:, 3]
        disagreement = float(np.median(np.sum((moved - target[good]) ** 2, axis=1))) / 3
        variances = (
            max(np.trace(pose_covariance[:3, :3]) / 3, config.min_rotation_sigma_rad**2),
            max(
                np.trace(pose_covariance[3:, 3:]) / 3,
                (config.min_translation_sigma * depth) ** 2,
                disagreement,
            ),
            max(_log_scale_variance(source[good], target[good]), config.min_log_scale_sigma**2),
        )
        covariance = np.diag(np.repeat(variances, (3, 3, 1)))
        correspondences = both[good][pnp_inliers]
        return Verification(*ids, True, "", matches, int(good.sum()), relative, covariance, correspondences)

    def _scene_agreement(self, query: Keyframe, match: Keyframe, relative: np.ndarray) -> tuple[int, int]:
        """(found, in view): the match's map points (off walking people) that ``relative``
        (match_from_query Sim(3)) puts in the query's image, and how many of them have a query keypoint within
        ``max_reprojection_error_px`` whose descriptor is within ``max_hamming`` bits."""
        assert match.points3d is not None
        # Points on walking people are not expected to be where the place puts them.
        kept = _unmasked(match, self.config.ignore_labels)
        mapped = kept[np.isfinite(match.points3d[kept]).all(axis=1)]
        query_from_match = np.linalg.inv(relative)
        in_query = match.points3d[mapped] @ query_from_match[:3, :3].T + query_from_match[:3, 3]
        # Points behind the camera project to NaN, which is never in view.
        pixels = np.asarray(self.camera.img_from_cam(in_query.astype(np.float64)), dtype=np.float64)
        seen = (
            (pixels[:, 0] >= 0) & (pixels[:, 0] < self.camera.width)
            & (pixels[:, 1] >= 0) & (pixels[:, 1] < self.camera.height)
        )  # fmt: skip
        if not seen.any() or len(query.keypoints) == 0:
            return 0, int(seen.sum())
        pairs = cKDTree(pixels[seen]).sparse_distance_matrix(
            cKDTree(np.asarray(query.keypoints, dtype=np.float64)),
            self.config.max_reprojection_error_px,
            output_type="ndarray",
        )
        point, keypoint = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
        distance = hamming(match.descriptors[mapped[seen][point]], query.descriptors[keypoint])
        return len(np.unique(point[distance <= self.config.max_hamming])), int(seen.sum())

    def _reprojected(
        self,
        match_from_query: np.ndarray,
        source: np.ndarray,
        target: np.ndarray,
        query_keypoints: np.ndarray,
        match_keypoints: np.ndarray,
    ) -> np.ndarray:
        """Which point pairs fit the 3x4 Sim(3) ``match_from_query`` in both images: the query's
        point lands near the match's keypoint and the match's point near the query's (in front of
        the camera, within ``max_reprojection_error_px``)."""
        query_from_match = np.linalg.inv(np.vstack((match_from_query, (0.0, 0.0, 0.0, 1.0))))[:3]
        limit = self.config.max_reprojection_error_px
        good = np.ones(len(source), dtype=bool)
        for points, transform, keypoints in (
            (source, match_from_query, match_keypoints),
            (target, query_from_match, query_keypoints),
        ):
            # Points behind the camera project to NaN, which is never within the limit.
            pixels = self.camera.img_from_cam(points @ transform[:, :3].T + transform[:, 3])
            good &= np.linalg.norm(pixels - keypoints, axis=1) <= limit
        return good

    def _pnp(
        self, query: Keyframe, match_points: np.ndarray, query_indices: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """match_from_query, its covariance and the inlier mask of ``query_indices``."""
        options = pycolmap.AbsolutePoseEstimationOptions()
        options.ransac.max_error = self.config.max_reprojection_error_px
        options.ransac.random_seed = self.config.seed
        result = pycolmap.estimate_and_refine_absolute_pose(
            query.keypoints[query_indices].astype(np.float64),
            match_points,
            self.camera,
            options,
            return_covariance=True,
        )
        if result is None or "covariance" not in result:
            return None
        query_from_match = np.eye(4)
        query_from_match[:3, :] = np.asarray(result["cam_from_world"].matrix(), dtype=np.float64)
        return (
            np.linalg.inv(query_from_match),
            np.asarray(result["covariance"], dtype=np.float64),
            np.asarray(result["inlier_mask"], dtype=bool),
        )


def _log_scale_variance(source: np.ndarray, target: np.ndarray) -> float:
    """Variance of the mean log ratio of point distances from the centroids (a scale estimate)."""
    a = np.linalg.norm(source - source.mean(axis=0), axis=1)
    b = np.linalg.norm(target - target.mean(axis=0), axis=1)
    keep = (a > 1e-9) & (b > 1e-9)
    logs = np.log(b[keep] / a[keep])
    return float(np.var(logs) / max(len(logs), 1))


def create(
    camera: CameraIntrinsics, overrides: Sequence[str] = (), config_path: Any = None
) -> PycolmapVerifier:
    return PycolmapVerifier(camera, load_config(VerifierConfig, config_path, overrides))
