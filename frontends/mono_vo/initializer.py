"""Two-view initialisation of a monocular map, following ORB-SLAM's rules with OpenCV's USAC.

The first frame with enough features becomes the reference. Each later frame is matched to it
(Lowe ratio, bounded image displacement); then an essential matrix and a homography are fitted with
seeded USAC. The homography is the model when it explains a large share of the inliers
(H / (H + E) > 0.45: a planar scene or a rotation), else the essential matrix. Every motion its
decomposition allows is scored by triangulating the inliers and counting points that lie in front
of both cameras, reproject within 2.45 px and see a parallax; the best must clearly beat the
runner-up, have enough points and a median parallax of at least 1 deg, and its direction of motion
must agree with the best hypotheses of the frames just before (``stable_frames`` in a row: the
camera moves smoothly, a poorly determined translation does not). Otherwise the frame is rejected
and the next one tried; once too few matches are left the reference moves on (ORB-SLAM's rule; a
frame count would be frame-rate dependent: a slow camera at 30 frames/s needs more than 30 frames
for 1 deg of parallax, docs/2026-12-06-slow-initialisation.md). When a
reference ran out of matches before ``stable_frames`` attempts (fast motion: no reference lives
that long), the next ones need only ``fast_motion_stable_frames`` agreeing frames.

The map frame is the reference camera and the first baseline has length 1 (the map's scale).
A fundamental matrix fitted to the same matches tells whether the intrinsics are plausible: with
wrong intrinsics, the essential matrix (which assumes them) keeps visibly fewer inliers than F.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from frontends.mono_vo.config import InitConfig
from frontends.mono_vo.features import Features
from frontends.mono_vo.geometry import check_triangulated, fit_or_none, frame_seed, triangulate, usac_params
from frontends.orb import match_descriptors

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Initialisation:
    """A successful two-view initialisation."""

    reference_index: int
    reference_timestamp: float
    reference: Features
    reference_image: np.ndarray
    #: World-to-camera pose of the current frame (reference = identity), unit baseline.
    T_cw: np.ndarray
    #: Matched feature indices in the reference and the current frame, and their world points.
    reference_idx: np.ndarray
    current_idx: np.ndarray
    points_w: np.ndarray
    #: Inliers of the essential matrix over inliers of the fundamental matrix (intrinsics check).
    essential_share: float
    median_parallax_deg: float


@dataclass(frozen=True)
class _Reference:
    index: int
    timestamp: float
    features: Features
    image: np.ndarray


class Initializer:
    def __init__(self, settings: InitConfig, K: np.ndarray, count_scale: float, seed: int, diagonal: float):
        self.settings = settings
        self.K = K
        self.min_matches = max(20, round(settings.min_matches * count_scale))
        self.min_points = max(20, round(settings.min_points * count_scale))
        self.seed = seed
        self.max_flow = settings.max_flow_fraction * diagonal
        self.reference: _Reference | None = None
        #: Directions (in the reference camera) of the last frames' best motion hypotheses.
        self.directions: list[np.ndarray] = []
        #: Agreeing frames needed: ``stable_frames``, fewer once a reference ran out of matches.
        self.stable_frames = settings.stable_frames

    def reset(self) -> None:
        self.reference = None
        self.directions = []
        self.stable_frames = self.settings.stable_frames

    def try_frame(
        self, index: int, timestamp: float, features: Features, image: np.ndarray
    ) -> Initialisation | None:
        reference = self.reference
        age = self.settings.max_reference_age
        if reference is None or (age > 0 and index - reference.index > age):
            self._set_reference(index, timestamp, features, image)
            return None
        ref_idx, cur_idx = match_descriptors(
            reference.features.descriptors, features.descriptors, self.settings.ratio, 100
        )
        flow = np.linalg.norm(reference.features.points[ref_idx] - features.points[cur_idx], axis=1)
        ref_idx, cur_idx = ref_idx[flow < self.max_flow], cur_idx[flow < self.max_flow]
        if len(ref_idx) < self.min_matches:
            if index - reference.index <= self.settings.stable_frames:
                self.stable_frames = min(self.stable_frames, self.settings.fast_motion_stable_frames)
            self._set_reference(index, timestamp, features, image)
            return None
        x1 = reference.features.points[ref_idx]
        x2 = features.points[cur_idx]
        result = self._reconstruct(x1, x2, index)
        if result is None:
            return None
        T_cw, good, points_w, essential_share, parallax = result
        return Initialisation(
            reference.index, reference.timestamp, reference.features, reference.image, T_cw,
            ref_idx[good], cur_idx[good], points_w[good], essential_share, parallax,
        )  # fmt: skip

    def _set_reference(self, index: int, timestamp: float, features: Features, image: np.ndarray) -> None:
        self.reference = _Reference(index, timestamp, features, image)
        self.directions = []

    def _reconstruct(
        self, x1: np.ndarray, x2: np.ndarray, index: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float] | None:
        s = self.settings
        K = self.K
        essential = fit_or_none(
            cv2.findEssentialMat, x1, x2, K, K, None, None,
            usac_params(frame_seed(self.seed, index, 1), s.essential_threshold),
        )  # fmt: skip
        homography = fit_or_none(
            cv2.findHomography, x1, x2, usac_params(frame_seed(self.seed, index, 2), s.homography_threshold)
        )
        fundamental = fit_or_none(
            cv2.findFundamentalMat,
            x1,
            x2,
            usac_params(frame_seed(self.seed, index, 3), s.essential_threshold),
        )
        if essential is None or essential[0] is None or essential[0].shape != (3, 3):
            return None
        E, e_mask = essential
        H, h_mask = homography if homography is not None else (None, None)
        F, f_mask = fundamental if fundamental is not None else (None, None)
        n_e = int(e_mask.sum())
        n_h = int(h_mask.sum()) if H is not None and h_mask is not None else 0
        n_f = int(f_mask.sum()) if F is not None and f_mask is not None else n_e
        essential_share = n_e / max(n_f, 1)
        use_homography = n_h / max(n_h + n_e, 1) > s.homography_share
        if use_homography and H is not None and h_mask is not None:
            count, rotations, translations, _ = cv2.decomposeHomographyMat(H, K)
            motions = [(rotations[i], translations[i].reshape(3)) for i in range(count)]
            inliers = h_mask.ravel().astype(bool)
        else:
            R1, R2, t = cv2.decomposeEssentialMat(E)
            motions = [(R, sign * t.reshape(3)) for R in (R1, R2) for sign in (1.0, -1.0)]
            inliers = e_mask.ravel().astype(bool)
        scored = []
        for rotation, translation in motions:
            norm = np.linalg.norm(translation)
            if norm < 1e-9:
                continue
            T_cw = np.eye(4)
            T_cw[:3, :3] = rotation
            T_cw[:3, 3] = translation / norm
            points_w = triangulate(K, np.eye(4), T_cw, x1, x2)
            good, parallax = check_triangulated(
                K, (np.eye(4), T_cw), (x1, x2), points_w, s.max_reprojection_px, 0.0
            )
            good &= inliers
            scored.append((int(good.sum()), T_cw, good, points_w, parallax))
        if not scored:
            return None
        scored.sort(key=lambda item: -item[0])
        best_count, T_cw, good, points_w, parallax = scored[0]
        runner_up = scored[1][0] if len(scored) > 1 else 0
        direction = -T_cw[:3, :3].T @ T_cw[:3, 3]  # the camera centre seen from the reference
        self.directions = [*self.directions, direction][-self.stable_frames :]
        # Points seen at a grazing parallax have poorly known depth: leave them for later keyframes.
        good &= parallax >= s.min_parallax_deg / 4
        best_count = int(good.sum())
        median_parallax = float(np.median(parallax[good])) if best_count else 0.0
        model = "homography" if use_homography else "essential"
        if best_count < self.min_points or median_parallax < s.min_parallax_deg:
            log.debug(
                "frame %d: init rejected (%s, %d points, median parallax %.2f deg)",
                index, model, best_count, median_parallax,
            )  # fmt: skip
            return None
        if best_count < s.ambiguity_ratio * runner_up:
            log.debug(
                "frame %d: init rejected (%s, ambiguous: %d vs %d)", index, model, best_count, runner_up
            )
            return None
        changes = [float(np.degrees(np.arccos(np.clip(d @ direction, -1, 1)))) for d in self.directions[:-1]]
        if len(changes) < self.stable_frames - 1 or max(changes, default=0.0) > s.max_direction_change_deg:
            log.debug("frame %d: init rejected (%s, direction not yet stable: %s)", index, model, changes)
            return None
        log.info(
            "initialised on frame %d (%s: %d points, median parallax %.2f deg, E/F inliers %.2f)",
            index, model, int(good.sum()), median_parallax, essential_share,
        )  # fmt: skip
        return T_cw, good, points_w, essential_share, median_parallax
