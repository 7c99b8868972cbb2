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
    #: Lowe ratio and the largest image displacement (fraction of the diagonal) of an init match.
    ratio: float = 0.8
    #: Largest image displacement of an init match (fraction of the image diagonal).
    max_flow_fraction: float = 0.25
    #: RANSAC thresholds (px) of the essential matrix (Sampson) and the homography (transfer); in
    #: the ratio of ORB-SLAM's chi2 cut-offs (5.99 vs 3.84), so that inlier counts are comparable.
    essential_threshold: float = 1.0
    #: Homography RANSAC threshold (px, transfer error).
    homography_threshold: float = 1.25
    #: Homography is the model when its share of the inliers H / (H + E) exceeds this (ORB-SLAM 0.45).
    homography_share: float = 0.45
    #: Triangulated points that must pass cheirality, reprojection and parallax checks.
    min_points: int = 80
    #: Median parallax angle (deg) of the good points (those above a quarter of it). ORB-SLAM's rule
    #: (the 50th largest >= 1 deg) accepted near-rotations with a wrong translation on small images.
    #: Measured alternatives, none better everywhere: 2 deg fixed synthetic loop 0 (a 1 deg start
    #: took forward motion with yaw for sideways motion, 36 % too much rotation, and the map's scale
    #: shrank 20x in 4 s; 1.37 -> 0.76 % ATE) and KITTI 06 (0.150 -> 0.111 %), but broke the 320x240
    #: loop 3 (1.7 -> 18.8 %); 3 deg never initialises on the KITTI clip.
    min_parallax_deg: float = 1.0
    #: The best motion hypothesis must have this many times the good points of the runner-up.
    ambiguity_ratio: float = 1.4
    #: ... and its direction of motion (the camera centre seen from the reference) must lie within
    #: ``max_direction_change_deg`` of the best hypotheses of the ``stable_frames`` - 1 frames
    #: before. During a turn with little translation the essential matrix's translation is poorly
    #: determined: synthetic loop seeds 0 and 1 initialised 87 and 99 deg off the true direction
    #: (after 3-4 frames at 1.2 deg/frame, two frames in a row agreeing on the wrong one), which
    #: distorted the first map; with three agreeing frames every synthetic start is within 13 deg.
    max_direction_change_deg: float = 10.0
    #: Consecutive attempts whose directions of motion must agree (see above).
    stable_frames: int = 3
    #: ... or this many after a reference ran out of matches (``min_matches``) before
    #: ``stable_frames`` attempts: at that speed no reference lives long enough for more, and the
    #: translation is large, not the poorly determined one of a turn. KITTI 06 at 5 Hz (2.4 m per
    #: frame) never initialised with 3.
    fast_motion_stable_frames: int = 2
    #: Reprojection error (px) of a triangulated point (sqrt of chi2(2 dof, 95 %) = 2.45).
    max_reprojection_px: float = 2.45
    #: Replace the reference frame after this many frames without an initialisation.
    max_reference_age: int = 30


@dataclass(frozen=True)
class TrackingConfig:
    #: Search radius (px) around the constant-velocity prediction, and after the PnP pose.
    search_radius: float = 15.0
    #: Search radius (px) around the PnP pose, for the second round of matches.
    refine_radius: float = 5.0
    #: Hamming distance of an accepted projection match, and Lowe's ratio between the best two.
    max_hamming: int = 80
    #: Lowe's ratio between the best two projection matches.
    ratio: float = 0.9
    #: A point is searched for only when the camera sees it within this angle of its mean viewing
    #: direction (ORB-SLAM: 60 deg) and within ``distance_margin`` of its scale-invariance range
    #: (ORB-SLAM: 0.8x the nearest, 1.2x the farthest distance).
    max_view_angle_deg: float = 60.0
    #: Margin on a point's scale-invariance distance range (ORB-SLAM: 0.8x and 1.2x).
    distance_margin: float = 1.2
    #: Orientation histogram of the matches (ORB-SLAM: 30 bins; the second and third most popular
    #: bins count with 10 % of the first's matches).
    rotation_bins: int = 30
    #: Share of the top bin's matches the second and third bins need to count (ORB-SLAM 0.1).
    rotation_min_share: float = 0.1
    #: PnP RANSAC reprojection threshold (px) and the inlier threshold of the refinement.
    pnp_threshold: float = 3.0
    #: Reprojection error (px) of an inlier of the pose refinement.
    inlier_threshold: float = 2.45
    #: Inliers needed to call a frame tracked (640x480 reference, scaled with the feature budget).
    min_inliers: int = 40
    #: Keyframes whose map points form the local map projected into each frame.
    local_keyframes: int = 10
    #: The tracked pose keeps the constant-velocity prediction's orientation within
    #: ``rotation_prior_acceleration`` x dt^2 deg (dt: seconds since the last tracked frame), a
    #: prior on the angular acceleration (``tracker.refine_with_rotation_prior``): 270 deg/s^2 is
    #: 0.3 deg at 30 Hz, 2.7 deg at 10 Hz, nothing after a gap. It matters only where the map is
    #: seen in a strip and rotation trades off against translation. 0: no prior.
    rotation_prior_acceleration: float = 270.0

    def __post_init__(self) -> None:
        if self.rotation_prior_acceleration < 0:
            raise ConfigError(
                "tracking: rotation_prior_acceleration must be >= 0 (0 turns the prior off), "
                f"got {self.rotation_prior_acceleration}"
            )


@dataclass(frozen=True)
class KeyframeConfig:
    #: A frame becomes a keyframe when it tracks fewer than ``tracked_ratio`` of the last keyframe's
    #: established points (seen by >= 3 keyframes; ORB-SLAM's rule) or ``min_tracked_share`` of all
    #: its points ...
    tracked_ratio: float = 0.9
    #: ... or fewer than this share of all its tracked points.
    min_tracked_share: float = 0.5
    #: ... or this much time passed since the last keyframe (s), and never sooner than min_interval.
    max_interval: float = 0.5
    #: Seconds since the last keyframe before another may be made.
    min_interval: float = 0.0
    #: ... or, at least ``narrow_min_interval`` s after the last keyframe, the tracked points span
    #: less than this share of the image width or height. A walking person or a turn into unmapped
    #: space can leave the map visible only in one strip, where the pose's translation is barely
    #: constrained; on the synthetic scenes tracking then lost the map's scale within ~10 frames
    #: unless a keyframe mapped the rest of the view. (Without the interval, keyframes a frame apart
    #: give local BA no baseline.)
    min_tracked_spread: float = 0.45
    #: Seconds since the last keyframe before a narrow spread makes one.
    narrow_min_interval: float = 0.1
    #: Earlier keyframes the new keyframe triangulates fresh points with, among the last
    #: ``triangulation_window`` that see the same scene (``partner_min_shared`` of its tracked map
    #: points; any when none does) with a baseline of at least ``min_baseline_ratio`` of its median
    #: depth: first the newest with ``preferred_baseline_ratio``, then the newest others. Keyframes
    #: that follow each other closely (a near object sweeping through the view) would otherwise only
    #: pair up with parallax-free neighbours. ``min_baseline_ratio`` 0.035 gives 2 deg at the median
    #: depth, twice ``min_parallax_deg``. A closer partner (ORB-SLAM's 0.01 gives 0.57 deg) leaves most
    #: points under the parallax limit, and those that pass it are the ones whose pixel noise widened
    #: their parallax, i.e. shortened their depth. Simulated (a test: 1 px noise, a wall 2-4 m away,
    #: sideways motion), partners 1 % of the median depth apart keep 1 % of the points, at depths 27 %
    #: short; 2 %: 58 %, 4 % short; 3.5 %: all, unbiased.
    #: Every keyframe that triangulates so shrinks the map a little more: during a walking person's
    #: pass, keyframes a frame apart shrank synthetic loop 2's map 20x. Measured over 84 masked runs
    #: (docs/slam-runs.md, "Triangulation baseline"): collapses 6 -> 2, restarts 3 -> 6 (loop closing
    #: links those). ``preferred_baseline_ratio`` 0.03 with ``partner_min_shared`` 0.2 is measured in
    #: docs/slam-runs.md ("Triangulation partners", under 0.01): it ended out-and-back 1's 8x collapse but
    #: made figure8 3's start shrink.
    triangulation_neighbours: int = 2
    #: Recent keyframes searched for triangulation partners.
    triangulation_window: int = 8
    #: Smallest baseline of a triangulation partner (fraction of the median depth).
    min_baseline_ratio: float = 0.035
    #: Baseline (fraction of the median depth) of the partners tried first.
    preferred_baseline_ratio: float = 0.035
    #: Share of the keyframe's tracked map points a partner must see (0: any).
    partner_min_shared: float = 0.0
    #: Search radius (fraction of the image diagonal) around the median-depth prediction of a match.
    search_fraction: float = 0.05
    #: Earlier keyframes the new keyframe's points are projected into (ORB-SLAM's SearchInNeighbors
    #: without the fusion of duplicates; 0: none), matched within ``search_radius`` px to keypoints
    #: without a map point. Points are then seen by more keyframes and more survive culling, and
    #: nearly all of a keyframe's points count as established, so pair it with ``tracked_ratio`` 0.7
    #: (at 0.9 almost every frame becomes a keyframe: synthetic loop 0, 173 of 300). Measured with 8
    #: and 0.7 (docs/slam-runs.md, "Search in neighbours"): KITTI clip 0.142 -> 0.094 % of the path; on the 21
    #: synthetic scenes of seeds 0-6 the runs that keep their map are 28-35 % more accurate, but 10
    #: of 42 masked runs (frontend seed 0 and 1) collapse against 7, so it is opt-in.
    search_neighbours: int = 0
    #: Radius (px) of the search in neighbouring keyframes and of duplicate fusion.
    search_radius: float = 3.0
    #: Duplicates: a local-map point that projects within ``search_radius`` px of a new keyframe's
    #: keypoint already holding another point, reprojects within the inlier threshold there and
    #: whose descriptor is within this Hamming distance of the keypoint's is the same scene point
    #: (tracking missed it, so the keyframe triangulated it again); the two are merged (ORB-SLAM's
    #: Fuse, TH_LOW 50). 0: never merge. Without it a quarter of the points a frame could match
    #: were copies (synthetic loop 6, frame 293: 106 of 376 unmatched points in view had their
    #: keypoint taken by a twin). Measured (docs/slam-runs.md, "Fusing duplicate points"): KITTI clip,
    #: frontend seeds 0-5, median ATE 0.173 -> 0.071 % of the path (better in 5 of 6); 84 masked synthetic
    #: runs (scene seeds 0-13) with a restart or collapse 19 -> 16, but the steady runs' geometric-
    #: mean ATE 8-16 % worse.
    fuse_max_hamming: int = 50
    #: Lowe ratio and Hamming limit of the keyframe-to-keyframe matches for triangulation.
    match_ratio: float = 0.8
    #: Hamming limit of a keyframe-to-keyframe triangulation match.
    match_max_hamming: int = 60
    #: Epipolar distance (px) of a triangulation match and the minimum parallax (deg) of its point.
    epipolar_threshold: float = 2.0
    #: Minimum parallax (deg) of a triangulated point.
    min_parallax_deg: float = 1.0
    #: Odometry covariance between consecutive keyframes (1-sigma) that share at least
    #: ``covariance_reference_points`` map points; the translation sigma is relative to the distance
    #: between the keyframes (the map has no metric unit). With fewer shared points every sigma
    #: grows as (reference / shared) ** ``covariance_exponent``, at most ``max_covariance_inflation``
    #: times. Measured against the GT on the 9 synthetic scenes (settled steps, 535 keyframes): the
    #: per-axis rotation error is 0.02-0.07 deg with > 500 shared points and 0.12-0.14 deg with
    #: 200-400, the translation direction error 1-2 % of the step and 28 % below 300 (errors grow as
    #: shared^-1.4 and shared^-2.9). Sigmas that ignored this made PCM reject the correct loops that
    #: span a thin stretch of map (figure8 seed 2: 14 of 32, to keyframes whose scale was 1.8x off).
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
    #: LM stops once an iteration lowers the error by less than this share: the local BA converges
    #: in 2-4 iterations, and the last ones moved the error by < 0.1 % (measured) at ~20 ms each.
    relative_error_tolerance: float = 1e-3
    #: Huber threshold in pixel sigmas; also the chi2-based outlier cut after the optimisation.
    huber_k: float = 2.45
    #: At a segment start (no older keyframes anchor the window) also hold the second keyframe's
    #: orientation, not only its distance from the first: the initialisation measured their
    #: relative rotation from hundreds of points. Facing a wall while turning and moving sideways,
    #: rotation and sideways translation move the image almost alike and, with the orientation
    #: free, each keyframe pulled the first pair further along that valley (figure8 seed 8: yaw
    #: under-estimated by 10, 20, 25 % per keyframe, the map shrinking 25x in 100 frames). Measured
    #: with the single-anchor range factor (``local_ba``; docs/slam-runs.md, "The segment start's
    #: orientation"), against False: first 200 frames of the 14 figure8 scenes x 2 frontend seeds,
    #: collapses 8 -> 1; 600-frame masked runs that restart or collapse 4 -> 2 of 42 (seeds 0-6) and
    #: 13 -> 7 of 42 (held-out 7-13); first 150 frames of the 320x240 loop x 10 frontend seeds,
    #: collapses 1 -> 0; but the KITTI clip's median ATE over frontend seeds 0-11 goes 0.071 ->
    #: 0.105 % of the path (all 12 below 0.3 %).
    start_orientation_prior: bool = True


@dataclass(frozen=True)
class RelocalisationConfig:
    #: Recent keyframes tried as anchors for a lost frame.
    max_keyframes: int = 12
    #: Lowe ratio of the matches between a lost frame and an anchor keyframe.
    ratio: float = 0.8
    #: PnP RANSAC inliers against one keyframe, and inliers after the local-map check (640x480 ref.).
    min_pnp_inliers: int = 20
    #: Inliers after the local-map check (640x480 reference).
    min_inliers: int = 50
    #: Frames with features that may fail to relocalise before a new map segment starts.
    patience: int = 10
    #: Frames with features and no pose (lost, or before the map's first keyframe) kept to be
    #: tracked backwards once the camera is posed again (the newest ones; 0 keeps none).
    backfill_frames: int = 90
    #: A frame tracked after the fact keeps its pose only if its inliers fix its camera centre
    #: (``geometry.relative_centre_sigma``) at most this many times as loosely as the frame that
    #: tracking resumed from. Tracked backwards from far away, a frame sees the map in a narrow
    #: strip where rotation and translation trade off: on figure8 seed 6 (init at frame 36, its
    #: centre fixed to 0.14 % of the depth) frames 11-18 were posed from 40-190 points at
    #: 0.5-1.6 % and ended 0.11-0.31 m off; the frames up to 3x (0.42 %) were 9-52 mm off. Such a
    #: frame stays unposed: nothing tracks on from it.
    backfill_max_sigma_ratio: float = 3.0
    #: A relocalised pose is kept only if its inliers fix its camera centre (``relative_centre_sigma``)
    #: at most this many times as loosely as the newest keyframe's points fix that keyframe's. After
    #: a blackout the camera sees the map's newest points in a strip, where PnP trades translation
    #: for rotation. Measured on 100 relocalisations (6 synthetic scenes, 20 black frames from frame
    #: 40, 70 or 100, resuming 20 frames on or 15 back, frontend seeds 0-2): where the map was right
    #: before the blackout (52 cases), the 7 relocalisations off by more than 5 % of the scene depth
    #: were at 5.2-23x, 37 of the 43 within 1.6 % at 0.8-3x (6 at 3.0-7.6x are refused); on young
    #: maps (blackout at frame 40) poses 0.34-0.49 m off came at 3.3-5x. A refused frame counts
    #: towards ``patience``: a new map segment, which loop closure reconnects, is better than a
    #: pose 0.2-0.6 m off.
    max_sigma_ratio: float = 3.0

    def __post_init__(self) -> None:
        hints = {
            "backfill_max_sigma_ratio": " (relocalisation.backfill_frames=0 turns backfilling off)",
            "max_sigma_ratio": "",
        }
        for key, hint in hints.items():
            if not getattr(self, key) > 0:
                raise ConfigError(f"relocalisation: {key} must be positive, got {getattr(self, key)}{hint}")


@dataclass(frozen=True)
class IntrinsicsCheckConfig:
    #: Warn when the essential matrix keeps less than this share of the fundamental matrix's inliers ...
    min_essential_share: float = 0.85
    #: ... or the bundle-adjusted median reprojection error of the first keyframes exceeds this (px).
    max_median_reprojection_px: float = 1.5
    #: Keyframes after which the reprojection check is made (once per segment).
    check_after_keyframes: int = 5


@dataclass(frozen=True)
class MaskingConfig:
    """Which detected movable objects a keyframe keeps out of the map (``masking``; the detector's
    boxes come through ``set_dynamic_objects``). DynaSLAM (monocular) masks every detected movable
    object; DS-SLAM masks a segmented person only when its points fail its epipolar check."""

    #: Judge each box on two-view evidence (moving, static, unknown); False masks every box as
    #: the detector gives it (DynaSLAM's monocular rule) and ignores ``min_unmasked_share``.
    check_motion: bool = True
    #: Lowe ratio and Hamming limit of the unguided keyframe-to-partner matches (ORB-SLAM's
    #: initialiser: 0.9 and TH_LOW 50; this frontend's triangulation: 0.8 and 60).
    match_ratio: float = 0.8
    #: Hamming limit of the keyframe-to-partner matches.
    max_hamming: int = 60
    #: Largest image displacement of a match (fraction of the image diagonal; init's 0.25).
    max_flow_fraction: float = 0.25
    #: A match violates the camera motion beyond this distance from its epipolar line (pyramid-level
    #: sigmas; sqrt of chi2(1 dof, 95 %) = 1.96, DS-SLAM uses 1 px) ...
    epipolar_sigmas: float = 2.0
    #: ... or when it triangulates behind a camera with at least this parallax (deg).
    min_parallax_deg: float = 1.0
    #: Matches a box needs for a verdict; fewer leave it "unknown".
    min_matches: int = 10
    #: A judged box is moving when its violations are too many to be chance (one-sided binomial
    #: test at ``significance``) at a rate of ``moving_ratio`` times the background's share (false
    #: matches, pose error), or ``min_violation_rate`` if higher; else it is static.
    moving_ratio: float = 2.0
    #: Smallest violation rate that makes a box moving.
    min_violation_rate: float = 0.1
    #: Significance level of the one-sided binomial test.
    significance: float = 0.01
    #: No verdict at all when more than this share of the background's matches violate the motion
    #: (KITTI clip: at most 0.16; a wrong pose, or boxes that leave only a strip just uncovered).
    max_background_share: float = 0.3
    #: A box overlapping a box judged moving in a keyframe at most ``follow_seconds`` before
    #: (intersection over union >= ``follow_iou``) is moving: an object moving parallel to the
    #: camera fits the epipolar geometry (at a wrong depth), and a walking person does not stop
    #: between two keyframes.
    follow_iou: float = 0.3
    #: Seconds a box judged moving makes overlapping boxes moving.
    follow_seconds: float = 1.0
    #: A box is static only if the median depth of its consistent matches is at most this many
    #: times that of the consistent matches around it (outside every box, within ``ring_fraction``
    #: of its size; at least ``min_ring_matches``): an object moving along the camera's direction
    #: fits the epipolar geometry at a wrong depth and, moving with the camera, lands behind what
    #: it hides (synthetic figure8 1: 2.2x and 1.6x; KITTI clip's parked cars: 0.1-1.1x).
    max_depth_ratio: float = 1.3
    #: Width of the ring around a box (fraction of its size) its depth is compared with.
    ring_fraction: float = 0.5
    #: Consistent matches the ring needs for the depth check.
    min_ring_matches: int = 5
    #: Keypoints outside the boxes matched to measure the background's share (seeded sample).
    background_sample: int = 300
    #: Boxes without a verdict, and static ones whose class may not be kept (people, animals), are
    #: masked only while this share of the keyframe's keypoints stays unmasked; moving boxes always
    #: are, static vehicles never (the provider's fifth value per box).
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
