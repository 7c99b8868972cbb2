"""Which of a detector's "movable" objects a new keyframe keeps out of the map: only those seen to
move, and never so much of the image that tracking starves.

A detector names classes that *can* move (people, cars). On a street most cars are parked, and
masking them took the near, high-parallax points tracking needs (the KITTI 06 clip: ATE 0.047 m
odometry alone, 0.086 m with every "car" masked; docs/2026-12-06-masking.md). So each box is
judged on two-view evidence, as DS-SLAM judges its segmented people (a motion-consistency check
on the epipolar geometry), against a partner keyframe whose pose is known:

1. The keypoints inside the boxes, in a ring around each (``ring_fraction`` of its size) and a seeded
   sample of the others are matched by descriptor to all of the partner's keypoints (Lowe's ratio
   test, bounded image displacement). The search is not guided by the poses: a guided search would
   find only what fits them.
2. A match violates the camera motion when it lies more than ``epipolar_sigmas`` (its pyramid
   level's sigma) from the epipolar line the two poses give, or when it triangulates behind one of
   the cameras with ``min_parallax_deg`` of parallax (an object that moves along the line, away
   from where the camera's own motion would take it).
3. The background's share of violations (false matches, pose error) is the yardstick: a box with
   ``min_matches`` matches is moving when its violations are too many to be chance (one-sided
   binomial test at ``significance``) at ``moving_ratio`` times the background's rate, or at
   ``min_violation_rate`` if higher. A background that violates more than ``max_background_share``
   leaves every box without a verdict.
4. An object moving along the camera's direction fits the epipolar geometry at a wrong depth:
   moving with the camera, behind what it hides. A box whose consistent matches lie more than
   ``max_depth_ratio`` times deeper than those around it is moving; one that passes both tests is
   static. Moving against the camera, it fits nearer than it is, where a parked car may also be:
   two views cannot tell, so a box that overlaps one judged moving in the keyframe before stays
   moving (``follow_iou``, ``follow_seconds``).

Moving boxes are masked. A box with too few matches to judge (small, far, textureless, or no
partner with a baseline) is masked as the detector says, but only while the keyframe keeps
``min_unmasked_share`` of its keypoints outside the masks. A static box is kept if its class may
be kept (a vehicle, often parked; the provider's fifth value per box); a person or an animal
stands still only for moments, and one walking towards the camera along its path fits both tests
at a shorter depth (the synthetic scenes' people walk in lanes beside the camera's path: judged
static, mapped, the map's scale collapsed), so it is masked like a box without a verdict.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from scipy.stats import binom

from frontends.mono_vo.config import MaskingConfig
from frontends.mono_vo.features import Features, octave_sigmas
from frontends.mono_vo.geometry import (
    check_triangulated,
    epipolar_distance,
    fundamental_from_poses,
    invert,
    project,
    transform,
    triangulate,
)
from frontends.orb import match_descriptors

Verdict = Literal["moving", "static", "unknown"]


@dataclass(frozen=True)
class BoxEvidence:
    """What the two-view check found for one box."""

    box: tuple[float, float, float, float]
    #: Keypoints of the keyframe inside the box.
    keypoints: int
    #: Of those, how many matched a partner keypoint, and how many of the matches violate the
    #: camera motion.
    matches: int
    violations: int
    #: Median depth of the box's consistent matches over that of the matches around it (nan when
    #: either has too few).
    depth_ratio: float
    verdict: Verdict


@dataclass(frozen=True)
class Partner:
    """The keyframe a new keyframe's boxes are checked against, or any posed view."""

    features: Features
    #: World-to-camera pose.
    T_cw: np.ndarray


def inside(keypoints: np.ndarray, box: Sequence[float]) -> np.ndarray:
    """(N,) which keypoints (pixel positions as detected) lie in the box (x0, y0, x1, y1, ...)."""
    x0, y0, x1, y1 = (float(v) for v in box[:4])
    return (keypoints[:, 0] >= x0) & (keypoints[:, 0] < x1) & (keypoints[:, 1] >= y0) & (keypoints[:, 1] < y1)


def motion_violations(
    features: Features,
    T_cw: np.ndarray,
    partner: Partner,
    query: np.ndarray,
    K: np.ndarray,
    octave_sigma: np.ndarray,
    diagonal: float,
    settings: MaskingConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Match the keypoints ``query`` (indices into ``features``) to the partner's; returns the
    matched keypoint indices and, per match, whether it violates the camera motion."""
    own, other = match_descriptors(
        features.descriptors[query], partner.features.descriptors, settings.match_ratio, settings.max_hamming
    )
    own = query[own]
    x_own, x_other = features.points[own], partner.features.points[other]
    near = np.linalg.norm(x_own - x_other, axis=1) <= settings.max_flow_fraction * diagonal
    own, other, x_own, x_other = own[near], other[near], x_own[near], x_other[near]
    sigma = octave_sigmas(octave_sigma, features.octaves[own])
    F = fundamental_from_poses(K, partner.T_cw, T_cw)
    off_line = epipolar_distance(F, x_other, x_own) > settings.epipolar_sigmas * sigma
    points_w = triangulate(K, partner.T_cw, T_cw, x_other, x_own)
    _, parallax = check_triangulated(K, (partner.T_cw, T_cw), (x_other, x_own), points_w, np.inf, 0.0)
    behind = np.zeros(len(own), bool)
    for pose in (partner.T_cw, T_cw):
        _, depth = project(K, pose, points_w)
        behind |= ~(np.nan_to_num(depth, nan=-1.0) > 0)
    behind &= parallax >= settings.min_parallax_deg
    depth = transform(T_cw, points_w)[:, 2] if len(points_w) else np.zeros(0)
    return own, off_line | behind, depth


def judge_boxes(
    boxes: Sequence[Sequence[float]],
    features: Features,
    T_cw: np.ndarray,
    partner: Partner | None,
    K: np.ndarray,
    octave_sigma: np.ndarray,
    diagonal: float,
    settings: MaskingConfig,
    seed: int,
) -> tuple[list[BoxEvidence], float]:
    """Each box's evidence and verdict, and the background's share of violating matches (nan
    without a partner or background matches)."""
    members = [inside(features.keypoints, box) for box in boxes]
    counts = [int(m.sum()) for m in members]
    unknown = [
        BoxEvidence(_box(box), n, 0, 0, float("nan"), "unknown") for box, n in zip(boxes, counts, strict=True)
    ]
    if partner is None or not boxes or len(partner.features) == 0:
        return unknown, float("nan")
    baseline = np.linalg.norm(invert(T_cw)[:3, 3] - invert(partner.T_cw)[:3, 3])
    if not baseline > 0:
        return unknown, float("nan")
    in_any = np.any(members, axis=0)
    outside = np.flatnonzero(~in_any)
    rng = np.random.default_rng(seed)
    if len(outside) > settings.background_sample:
        outside = np.sort(rng.choice(outside, settings.background_sample, replace=False))
    rings = [inside(features.keypoints, _grown(box, settings.ring_fraction)) & ~in_any for box in boxes]
    near = np.any(rings, axis=0)
    query = np.union1d(np.flatnonzero(in_any | near), outside)
    matched, violates, depth = motion_violations(
        features, T_cw, partner, query, K, octave_sigma, diagonal, settings
    )
    background = ~in_any[matched]
    background_share = float(violates[background].mean()) if background.any() else float("nan")
    if background_share > settings.max_background_share:
        # The camera motion itself is in doubt (or the boxes leave only a strip the objects just
        # uncovered): no verdict either way.
        return unknown, background_share
    expected = max(
        settings.min_violation_rate, settings.moving_ratio * np.nan_to_num(background_share, nan=0.0)
    )
    evidence = []
    for box, member, ring, count in zip(boxes, members, rings, counts, strict=True):
        hit = member[matched]
        n, bad = int(hit.sum()), int(violates[hit].sum())
        around = depth[ring[matched] & ~violates]
        ratio = float("nan")
        if n - bad > 0 and len(around) >= settings.min_ring_matches:
            ratio = float(np.median(depth[hit & ~violates]) / np.median(around))
        verdict: Verdict = "unknown"
        if n >= settings.min_matches:
            chance = float(binom.sf(bad - 1, n, expected))
            if chance < settings.significance or ratio > settings.max_depth_ratio:
                verdict = "moving"
            elif ratio <= settings.max_depth_ratio:
                verdict = "static"
        evidence.append(BoxEvidence(_box(box), count, n, bad, ratio, verdict))
    return evidence, background_share


def follow_moving(
    evidence: Sequence[BoxEvidence], moving_before: Sequence[Sequence[float]], min_iou: float
) -> list[BoxEvidence]:
    """The evidence with every box that overlaps (intersection over union >= ``min_iou``) a box
    judged moving in the keyframe before judged moving too."""
    return [
        replace(e, verdict="moving") if any(iou(e.box, other) >= min_iou for other in moving_before) else e
        for e in evidence
    ]


def iou(a: Sequence[float], b: Sequence[float]) -> float:
    """Intersection over union of two boxes (x0, y0, x1, y1)."""
    width = min(a[2], b[2]) - max(a[0], b[0])
    height = min(a[3], b[3]) - max(a[1], b[1])
    if width <= 0 or height <= 0:
        return 0.0
    overlap = width * height
    return float(overlap / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - overlap))


def dynamic_keypoints(
    keypoints: np.ndarray,
    evidence: Sequence[BoxEvidence],
    may_keep: Sequence[bool],
    settings: MaskingConfig,
) -> np.ndarray:
    """(N,) the keypoints to keep out of the map: those in moving boxes; then, smallest box first,
    while ``min_unmasked_share`` of them stays unmasked, those in boxes without a verdict and in
    static boxes that may not be kept (``may_keep`` False: people and animals stand still only for
    moments)."""
    dynamic = np.zeros(len(keypoints), bool)
    for item in evidence:
        if item.verdict == "moving":
            dynamic |= inside(keypoints, item.box)
    floor = settings.min_unmasked_share * len(keypoints)
    doubtful = [
        e
        for e, keep in zip(evidence, may_keep, strict=True)
        if e.verdict == "unknown" or (e.verdict == "static" and not keep)
    ]
    for item in sorted(doubtful, key=lambda e: e.keypoints):
        grown = dynamic | inside(keypoints, item.box)
        if len(keypoints) - int(grown.sum()) >= floor:
            dynamic = grown
    return dynamic


def _box(box: Sequence[float]) -> tuple[float, float, float, float]:
    x0, y0, x1, y1 = (float(v) for v in box[:4])
    return x0, y0, x1, y1


def _grown(box: Sequence[float], fraction: float) -> tuple[float, float, float, float]:
    x0, y0, x1, y1 = _box(box)
    dx, dy = fraction * (x1 - x0), fraction * (y1 - y0)
    return x0 - dx, y0 - dy, x1 + dx, y1 + dy
