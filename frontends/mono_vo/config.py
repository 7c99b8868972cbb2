"""Configuration of the monocular VO frontend: one frozen dataclass per stage, all with defaults.

Pixel thresholds are for the undistorted image at pyramid level 0; a keypoint detected at pyramid
level ``o`` gets ``scale_factor**o`` times the tolerance (its position is that much coarser). Counts
that depend on how many features an image has (minimum matches, minimum points) are given for the
reference 640x480 image and scaled with the image's feature budget.

Every random choice (OpenCV USAC RANSAC in initialisation, PnP and relocalisation) draws its state
from ``MonoVoConfig.seed`` mixed with the frame index, never from OpenCV's global RNG.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from frontends.errors import ConfigError
from frontends.orb import TRACKING_ORB, OrbConfig


@dataclass(frozen=True)
class InitConfig:
    """Two-view initialisation (ORB-SLAM's model selection and acceptance rules)."""

    #: Matches between the reference and the current frame needed to attempt (else new reference).
    min_matches: int = 100
    #: Lowe ratio of an init match.
    ratio: float = 0.8
    #: Largest image displacement of an init match (fraction of the image diagonal).
    max_flow_fraction: float = 0.25
    #: Essential-matrix RANSAC threshold (px, Sampson); vs homography: ORB-SLAM's chi2 3.84 vs 5.99.
    essential_threshold: float = 1.0
    #: Homography RANSAC threshold (px, transfer error).
    homography_threshold: float = 1.25
    #: Homography is the model when its share of the inliers H / (H + E) exceeds this (ORB-SLAM 0.45).
    homography_share: float = 0.45
    #: Triangulated points that must pass cheirality, reprojection and parallax checks.
    min_points: int = 80
    #: Median parallax (deg) of the good points (ORB-SLAM: 50th >= 1 deg) (docs/2026-12-06-config-evidence.md)
    min_parallax_deg: float = 1.0
    #: The best motion hypothesis must have this many times the good points of the runner-up.
    ambiguity_ratio: float = 1.4
    #: Largest change (deg) of motion direction over ``stable_frames`` (docs/2026-12-06-config-evidence.md)
    max_direction_change_deg: float = 10.0
    #: Consecutive attempts whose directions of motion must agree within ``max_direction_change_deg``.
    stable_frames: int = 3
    #: ``stable_frames`` after a reference ran out of matches early (docs/2026-12-06-config-evidence.md)
    fast_motion_stable_frames: int = 2
    #: Reprojection error (px) of a triangulated point (sqrt of chi2(2 dof, 95 %) = 2.45).
    max_reprojection_px: float = 2.45
    #: Replace the reference after this many frames; 0: only once its matches run out (ORB-SLAM's rule)
    max_reference_age: int = 0

    def __post_init__(self) -> None:
        if self.max_reference_age < 0:
            raise ConfigError("init: max_reference_age must be >= 0 (0: the reference ages with its matches)")


@dataclass(frozen=True)
class TrackingConfig:
    #: Search radius (px) around the constant-velocity prediction, and after the PnP pose.
    search_radius: float = 15.0
    #: Search radius (px) around the PnP pose, for the second round of matches.
    refine_radius: float = 5.0
    #: Hamming distance of an accepted projection match.
    max_hamming: int = 80
    #: Lowe's ratio between the best two projection matches.
    ratio: float = 0.9
    #: Largest angle (deg) from a point's mean viewing direction at which it is searched (ORB-SLAM: 60).
    max_view_angle_deg: float = 60.0
    #: Margin on a point's scale-invariance distance range (ORB-SLAM: 0.8x and 1.2x).
    distance_margin: float = 1.2
    #: Bins of the matches' orientation histogram (ORB-SLAM: 30).
    rotation_bins: int = 30
    #: Share of the top bin's matches the second and third bins need to count (ORB-SLAM 0.1).
    rotation_min_share: float = 0.1
    #: PnP RANSAC reprojection threshold (px).
    pnp_threshold: float = 3.0
    #: Reprojection error (px) of an inlier of the pose refinement.
    inlier_threshold: float = 2.45
    #: Inliers needed to call a frame tracked (640x480 reference, scaled with the feature budget).
    min_inliers: int = 40
    #: Keyframes whose map points form the local map projected into each frame.
    local_keyframes: int = 10
    #: Experimental: older covisible keyframes adding points to the local map (docs/2026-12-07-slow-camera.md)
    covisible_keyframes: int = 0
    #: Keyframes before the newest searched for its covisible ones.
    covisible_reach: int = 64
    #: Shared map points that make two keyframes covisible (ORB-SLAM: 15).
    covisible_min_shared: int = 15
    #: Angular-acceleration prior (deg/s^2) on the orientation; 0: none (docs/2026-12-06-config-evidence.md)
    rotation_prior_acceleration: float = 270.0

    def __post_init__(self) -> None:
        if self.covisible_keyframes < 0 or self.covisible_reach < 0 or self.covisible_min_shared < 1:
            raise ConfigError(
                "tracking: covisible_keyframes and covisible_reach must be >= 0 and covisible_min_shared >= 1"
            )
        if self.rotation_prior_acceleration < 0:
            raise ConfigError(
                "tracking: rotation_prior_acceleration must be >= 0 (0 turns the prior off), "
                f"got {self.rotation_prior_acceleration}"
            )


@dataclass(frozen=True)
class KeyframeConfig:
    #: Keyframe when tracking fewer than this share of the last keyframe's points seen by >= 3 keyframes.
    tracked_ratio: float = 0.9
    #: Keyframe when tracking fewer than this share of all the last keyframe's map points.
    min_tracked_share: float = 0.5
    #: Keyframe when this much time (s) passed since the last one (never sooner than ``min_interval``).
    max_interval: float = 0.5
    #: Seconds since the last keyframe before another may be made.
    min_interval: float = 0.0
    #: Keyframe when tracked points span < this share of the image side (docs/2026-12-06-config-evidence.md)
    min_tracked_spread: float = 0.45
    #: Seconds since the last keyframe before a narrow spread makes one.
    narrow_min_interval: float = 0.1
    #: Earlier keyframes the new keyframe triangulates fresh points with (docs/2026-12-06-config-evidence.md)
    triangulation_neighbours: int = 2
    #: Recent keyframes searched for triangulation partners.
    triangulation_window: int = 8
    #: Keyframes searched back when the window has no baseline (slow camera; docs/2026-12-07-slow-camera.md)
    triangulation_reach: int = 64
    #: Share of the tracked points an older partner (beyond the window) must see.
    far_partner_min_shared: float = 0.25
    #: Smallest baseline of a triangulation partner (fraction of the median depth).
    min_baseline_ratio: float = 0.035
    #: Experimental: baseline (of median depth) of partners tried first (docs/2026-12-06-config-evidence.md)
    preferred_baseline_ratio: float = 0.035
    #: Experimental: share of tracked map points a partner sees (0: any) (docs/2026-12-06-config-evidence.md)
    partner_min_shared: float = 0.0
    #: Search radius (fraction of the image diagonal) around the median-depth prediction of a match.
    search_fraction: float = 0.05
    #: Experimental: older keyframes new points are searched in (0: none) (docs/2026-12-06-config-evidence.md)
    search_neighbours: int = 0
    #: Radius (px) of the search in neighbouring keyframes and of duplicate fusion.
    search_radius: float = 3.0
    #: Hamming limit to merge duplicate points (ORB-SLAM 50; 0: never) (docs/2026-12-06-config-evidence.md)
    fuse_max_hamming: int = 50
    #: Lowe ratio of the keyframe-to-keyframe matches for triangulation.
    match_ratio: float = 0.8
    #: Hamming limit of a keyframe-to-keyframe triangulation match.
    match_max_hamming: int = 60
    #: Epipolar distance (px) of a triangulation match.
    epipolar_threshold: float = 2.0
    #: Minimum parallax (deg) of a triangulated point.
    min_parallax_deg: float = 1.0
    #: Odometry rotation sigma (deg per axis) at full covisibility (docs/2026-12-06-config-evidence.md)
    rotation_sigma_deg: float = 0.1
    #: Odometry translation sigma (fraction of the step length).
    translation_sigma_ratio: float = 0.02
    #: Odometry log-scale sigma.
    log_scale_sigma: float = 0.005
    #: Shared map points at and above which the sigmas are not inflated.
    covariance_reference_points: int = 400
    #: Sigmas grow as (reference / shared points) ** this.
    covariance_exponent: float = 2.0
    #: Largest factor the sigmas are inflated by.
    max_covariance_inflation: float = 100.0

    def __post_init__(self) -> None:
        if self.search_neighbours < 0 or not self.search_radius > 0:
            raise ConfigError(
                "keyframes: search_neighbours must be >= 0 (0 turns the search off) and search_radius > 0"
            )
        if self.fuse_max_hamming < 0:
            raise ConfigError("keyframes: fuse_max_hamming must be >= 0 (0 turns the fusion off)")
        if self.triangulation_reach < self.triangulation_window or not 0 <= self.far_partner_min_shared <= 1:
            raise ConfigError(
                "keyframes: triangulation_reach must be >= triangulation_window and far_partner_min_shared "
                f"within [0, 1], got {self.triangulation_reach} and {self.far_partner_min_shared}"
            )
        if self.covariance_reference_points < 1 or self.covariance_exponent < 0:
            raise ConfigError(
                "keyframes: covariance_reference_points must be >= 1 and covariance_exponent >= 0"
            )
        if self.max_covariance_inflation < 1:
            raise ConfigError(
                f"keyframes: max_covariance_inflation must be >= 1, got {self.max_covariance_inflation}"
            )


@dataclass(frozen=True)
class BundleAdjustmentConfig:
    #: Run local bundle adjustment after each keyframe.
    enabled: bool = True
    #: Keyframes optimised after each new keyframe (older ones that see the same points stay fixed).
    window: int = 6
    #: Fixed keyframes (outside the window) that anchor the window, most recent first.
    max_fixed: int = 4
    #: Levenberg-Marquardt iterations at most.
    iterations: int = 6
    #: LM stops when an iteration gains less than this share (docs/2026-12-06-config-evidence.md)
    relative_error_tolerance: float = 1e-3
    #: Huber threshold in pixel sigmas; also the chi2-based outlier cut after the optimisation.
    huber_k: float = 2.45
    #: Also hold the second keyframe's orientation at a segment start (docs/2026-12-06-config-evidence.md)
    start_orientation_prior: bool = True


@dataclass(frozen=True)
class RelocalisationConfig:
    #: Recent keyframes tried as anchors for a lost frame.
    max_keyframes: int = 12
    #: Lowe ratio of the matches between a lost frame and an anchor keyframe.
    ratio: float = 0.8
    #: PnP RANSAC inliers against one keyframe (640x480 reference).
    min_pnp_inliers: int = 20
    #: Inliers after the local-map check (640x480 reference).
    min_inliers: int = 50
    #: Frames with features that may fail to relocalise before a new map segment starts.
    patience: int = 10
    #: Seconds lost a new segment also waits for; 0: off (ORB-SLAM3: 3) (docs/2026-12-06-walking-people.md)
    patience_s: float = 0.0
    #: Unposed frames (the newest) kept to be tracked backwards once the camera is posed; 0: none.
    backfill_frames: int = 90
    #: Largest centre sigma of a backfilled frame (x the resumed frame's) (docs/2026-12-06-config-evidence.md)
    backfill_max_sigma_ratio: float = 3.0
    #: Largest centre sigma of a relocalised pose (x newest keyframe's) (docs/2026-12-06-config-evidence.md)
    max_sigma_ratio: float = 3.0

    def __post_init__(self) -> None:
        hints = {
            "backfill_max_sigma_ratio": " (relocalisation.backfill_frames=0 turns backfilling off)",
            "max_sigma_ratio": "",
        }
        for key, hint in hints.items():
            if not getattr(self, key) > 0:
                raise ConfigError(f"relocalisation: {key} must be positive, got {getattr(self, key)}{hint}")
        if not self.patience_s >= 0:
            raise ConfigError(f"relocalisation: patience_s must be >= 0, got {self.patience_s}")


@dataclass(frozen=True)
class IntrinsicsCheckConfig:
    #: Warn when the essential matrix keeps less than this share of the fundamental matrix's inliers.
    min_essential_share: float = 0.85
    #: Warn when the bundle-adjusted median reprojection error (px) of the first keyframes exceeds this.
    max_median_reprojection_px: float = 1.5
    #: Keyframes after which the reprojection check is made (once per segment).
    check_after_keyframes: int = 5


@dataclass(frozen=True)
class MaskingConfig:
    """Which detected movable objects a keyframe keeps out of the map (``masking``; the detector's
    boxes come through ``set_dynamic_objects``). DynaSLAM (monocular) masks every detected movable
    object; DS-SLAM masks a segmented person only when its points fail its epipolar check."""

    #: Experimental: False masks every box as detected (DynaSLAM's rule) (docs/2026-12-06-config-evidence.md)
    check_motion: bool = True
    #: Lowe ratio of the unguided keyframe-to-partner matches (ORB-SLAM's initialiser: 0.9).
    match_ratio: float = 0.8
    #: Hamming limit of the keyframe-to-partner matches (ORB-SLAM's initialiser: TH_LOW 50).
    max_hamming: int = 60
    #: Largest image displacement of a match (fraction of the image diagonal; init's 0.25).
    max_flow_fraction: float = 0.25
    #: Epipolar distance (level sigmas) beyond which a match violates the motion (DS-SLAM: 1 px).
    epipolar_sigmas: float = 2.0
    #: A match behind a camera also violates the motion when its parallax (deg) is at least this.
    min_parallax_deg: float = 1.0
    #: Matches a box needs for a verdict; fewer leave it "unknown".
    min_matches: int = 10
    #: A box is moving when its violation rate is significantly above this many times the background's.
    moving_ratio: float = 2.0
    #: Smallest violation rate that makes a box moving.
    min_violation_rate: float = 0.1
    #: Significance level of the one-sided binomial test.
    significance: float = 0.01
    #: No verdicts above this share of violating background matches (docs/2026-12-06-config-evidence.md)
    max_background_share: float = 0.3
    #: IoU with a recent moving box that makes a box moving (docs/2026-12-06-config-evidence.md)
    follow_iou: float = 0.3
    #: Seconds a box judged moving makes overlapping boxes moving.
    follow_seconds: float = 1.0
    #: Largest median depth of a static box (x its surrounding ring's) (docs/2026-12-06-config-evidence.md)
    max_depth_ratio: float = 1.3
    #: Width of the ring around a box (fraction of its size) its depth is compared with.
    ring_fraction: float = 0.5
    #: Consistent matches the ring needs for the depth check.
    min_ring_matches: int = 5
    #: Keypoints outside the boxes matched to measure the background's share (seeded sample).
    background_sample: int = 300
    #: Unknown boxes, and static people and animals, are masked only while this keypoint share stays free.
    min_unmasked_share: float = 0.6

    def __post_init__(self) -> None:
        shares = ("min_violation_rate", "significance", "min_unmasked_share", "max_background_share")
        positive = ("max_flow_fraction", "epipolar_sigmas", "moving_ratio", "max_depth_ratio")
        counts = ("min_matches", "min_ring_matches", "background_sample")
        bad = [f"{key} must be in [0, 1]" for key in shares if not 0 <= getattr(self, key) <= 1]
        bad += [f"{key} must be positive" for key in positive if not getattr(self, key) > 0]
        bad += [f"{key} must be >= 1" for key in counts if not getattr(self, key) >= 1]
        bad += [f"{key} must be >= 0" for key in ("min_parallax_deg", "follow_seconds", "ring_fraction")
                if not getattr(self, key) >= 0]  # fmt: skip
        if not 0 < self.match_ratio <= 1:
            bad.append("match_ratio must be in (0, 1]")
        if not 0 < self.follow_iou <= 1:
            bad.append("follow_iou must be in (0, 1]")
        if bad:
            raise ConfigError(f"masking: {'; '.join(bad)}")


@dataclass(frozen=True)
class MonoVoConfig:
    #: Seed of every RANSAC (initialisation, PnP, relocalisation), mixed with the frame index.
    seed: int = 0
    #: Frames with fewer features than this (640x480 reference) are "lost" without further work.
    min_features: int = 100
    #: ORB extraction (``frontends.orb``; the tracking preset: dense, spread, two thresholds per cell).
    orb: OrbConfig = field(default_factory=lambda: TRACKING_ORB)
    #: Two-view initialisation of a map (``InitConfig``).
    init: InitConfig = field(default_factory=InitConfig)
    #: Tracking each frame against the local map (``TrackingConfig``).
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    #: Keyframe selection, triangulation and odometry covariance (``KeyframeConfig``).
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    #: Local bundle adjustment after each keyframe (``BundleAdjustmentConfig``).
    ba: BundleAdjustmentConfig = field(default_factory=BundleAdjustmentConfig)
    #: Recovering a lost frame, and backfilling frames before the map (``RelocalisationConfig``).
    relocalisation: RelocalisationConfig = field(default_factory=RelocalisationConfig)
    #: Warnings that the camera intrinsics look wrong (``IntrinsicsCheckConfig``).
    intrinsics_check: IntrinsicsCheckConfig = field(default_factory=IntrinsicsCheckConfig)
    #: Which movable-object boxes are masked from tracking (``MaskingConfig``).
    masking: MaskingConfig = field(default_factory=MaskingConfig)
