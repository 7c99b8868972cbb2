"""Global bundle adjustment after loop closing (ORB-SLAM's full BA after the pose graph).

The pose graph moves each keyframe as a whole; what its map points say about the poses between
loops is summarised by one odometry covariance per step. Full bundle adjustment over every
keyframe and map point, started at the pose graph's estimate, uses them all, and ties the two
visits of a loop through the map itself: the query keyframe also observes the match keyframe's
points at the keypoints the verifier paired with them (and the match the query's). Then, as
ORB-SLAM fuses the duplicated points of a loop, every adjusted point is sought in every keyframe
that does not observe it yet (projection, then ORB descriptor) and the map is adjusted again with
what was found: a loop's correspondences tie a few keyframe pairs, fusion ties every keyframe of
one visit to the points of the other it sees.

Input is frontend-agnostic: keyframes with ``point_ids`` (map point of each keypoint, unique within
the keyframe's segment) and ``points3d`` (its camera-frame position in the keyframe's units), the
backend's camera-to-world Sim(3) estimate of each, and the verified correspondences of the accepted
loops. A point starts where its oldest observing keyframe's estimate puts it. Variables are the
keyframes' SE(3) poses and the points' world positions, factors GTSAM projection factors on
undistorted pixels with a Huber kernel, each with its keypoint's sigma (``Keyframe.keypoint_sigmas``:
an ORB keypoint found on a coarser pyramid level is located less precisely, as in the frontend's
local bundle adjustment). Gauge: a weak prior on every keyframe's start (see ``_add_gauge``).

Afterwards each keyframe's Sim(3) is its adjusted pose with the scale that maps its ``points3d``
onto the adjusted points (median distance ratio), so frames posed relative to a keyframe (in its
units) follow it.

Bounds: keyframes mapping under ``weak_keyframe_share`` of the median keyframe's points (where
tracking degrades before a loss; a keyframe without points) are left out and take the correction of
their segment's nearest adjusted keyframe; above ``max_observations`` an evenly spaced share of the
points is adjusted, so time and memory do not grow with the map's density
(docs/2026-12-06-long-runs.md).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import gtsam
import numpy as np
import pycolmap
from scipy.spatial import cKDTree

from frontends.base import PointObservations
from frontends.errors import ConfigError
from frontends.types import CameraIntrinsics, Keyframe
from slam_backend.lie import as_4x4

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GlobalBundleAdjustmentConfig:
    #: Run it when the stream ends, if any loop was accepted.
    enabled: bool = True
    #: Keypoint position noise (px) at the finest detection scale (times the keyframe's ``keypoint_sigmas``).
    pixel_sigma: float = 1.0
    #: Huber kernel threshold in sigmas (chi2 95 %, 2 dof).
    huber_k: float = 2.447
    #: Levenberg-Marquardt iterations at most (docs/2026-12-06-config-evidence.md)
    iterations: int = 10
    #: Levenberg-Marquardt stops when an iteration gains less than this share.
    relative_error_tolerance: float = 1e-3
    #: LM stops when a step needs more damping than this (x the Hessian's diagonal; GTSAM's 1e5).
    max_lambda: float = 0.1
    #: Points observed by fewer keyframes do not constrain poses.
    min_observations: int = 2
    #: Re-pose every frame posed from map points against the adjusted points (else it follows its keyframes).
    repose_frames: bool = True
    #: Observations a re-posed frame needs within ``frame_max_error_px``.
    frame_min_inliers: int = 20
    #: Reprojection error (px) of an inlier of a re-posed frame.
    frame_max_error_px: float = 4.0
    #: Observations within this many times ``frame_max_error_px`` start the refinement.
    frame_search_factor: float = 3.0
    #: Radius (px) of the search for points a keyframe does not observe yet, after a first adjustment; 0: off.
    fuse_radius_px: float = 4.0
    #: Hamming limit (bits) of a fused observation (ORB-SLAM's TH_LOW 50).
    fuse_max_hamming: int = 50
    #: Keyframes mapping under this share of the median keyframe's points follow their neighbours; 0: none.
    weak_keyframe_share: float = 0.25
    #: Observations at most (above: an evenly spaced share of the points; memory and time bounded); 0: all.
    max_observations: int = 100_000
    #: Map-point observations kept per frame to re-pose it (evenly spaced; 200 cost loop 2 18 % ATE); 0: all.
    frame_max_observations: int = 0
    #: Bound (MB) of the elimination's largest clique (symbolic estimate; peak RSS ~250 MB above); 0: none.
    max_gather_mb: float = 512.0

    def __post_init__(self) -> None:
        if self.pixel_sigma <= 0 or self.huber_k <= 0:
            raise ConfigError("global_ba: pixel_sigma and huber_k must be positive")
        if not self.max_lambda > 0:
            raise ConfigError("global_ba: max_lambda must be positive")
        if self.iterations < 1 or self.min_observations < 2:
            raise ConfigError("global_ba: iterations must be >= 1 and min_observations >= 2")
        if self.fuse_radius_px < 0 or not 0 < self.fuse_max_hamming <= 256:
            raise ConfigError("global_ba: fuse_radius_px must be >= 0 and fuse_max_hamming in 1..256")
        if self.max_observations < 0 or self.frame_max_observations < 0:
            raise ConfigError("global_ba: max_observations and frame_max_observations must be >= 0 (0: all)")
        if not 0 <= self.weak_keyframe_share < 1:
            raise ConfigError("global_ba: weak_keyframe_share must be in [0, 1)")
        if self.max_gather_mb < 0:
            raise ConfigError("global_ba: max_gather_mb must be >= 0 (0: no bound)")


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
    #: Observations of points by keyframes that had them as duplicates or not at all (fusion).
    fused_observations: int
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
    #: Keyframes left out as weakly mapped (``weak_keyframe_share``): each follows its nearest
    #: adjusted keyframe, and frames posed from them follow them instead of being posed again.
    followers: frozenset[int] = frozenset()

    @functools.cached_property
    def _row_lookup(self) -> dict[int, np.ndarray]:
        """Per segment, the row of each point id (-1 where none): one gather per re-posed frame."""
        by_segment: dict[int, list[tuple[int, int]]] = {}
        for (segment, point_id), row in self.point_rows.items():
            by_segment.setdefault(segment, []).append((point_id, row))
        lookup = {}
        for segment, pairs in by_segment.items():
            ids, rows = np.array(pairs, np.int64).T
            table = np.full(int(ids.max()) + 1 if len(ids) else 0, -1, np.int64)
            table[ids[ids >= 0]] = rows[ids >= 0]
            lookup[segment] = table
        return lookup

    def positions(self, segment: int, point_ids: np.ndarray) -> np.ndarray:
        """World positions of a segment's points (NaN rows for points the adjustment left out)."""
        lookup = self._row_lookup.get(segment)
        ids = np.asarray(point_ids, np.int64)
        rows = np.full(len(ids), -1, np.int64)
        if lookup is not None:
            inside = (ids >= 0) & (ids < len(lookup))
            rows[inside] = lookup[ids[inside]]
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
    weak = _weak_keyframes(by_id, config.weak_keyframe_share)
    segment_of = {kf_id: kf.segment for kf_id, kf in by_id.items()}
    by_id = {kf_id: kf for kf_id, kf in by_id.items() if kf_id not in weak}
    observed = _collect_observations(by_id, loops, camera)
    if observed is None:
        return None
    positions = _initial_points(by_id, estimates, observed)
    seen = np.bincount(observed.point_index, minlength=len(observed.keys))
    # Keyframes seeing the same point twice (a loop observation) still count once here: close enough.
    kept = np.isfinite(positions).all(axis=1) & (seen >= config.min_observations)
    kept = _thinned(kept, seen, config.max_observations)
    observed = observed.subset(kept[observed.point_index])
    if len(observed.point_index) == 0:
        return None
    poses = {k: as_4x4(estimates[k]) for k in np.unique(observed.keyframe_ids).tolist()}
    before = _reprojection_errors(poses, positions, observed, camera)
    solved = _solve(poses, positions, observed, camera, config)
    if solved is None:
        return None
    poses, positions = solved
    fused = 0
    if config.fuse_radius_px > 0:
        extra = _fused_observations(by_id, poses, positions, observed, camera, config)
        if len(extra.point_index):
            again = _solve(poses, positions, observed.joined(extra), camera, config)
            if again is not None:
                poses, positions = again
                observed, fused = observed.joined(extra), len(extra.point_index)
    after = _reprojection_errors(poses, positions, observed, camera)

    adjusted_points = np.full((len(observed.keys), 3), np.nan)
    used = np.unique(observed.point_index)
    adjusted_points[used] = positions[used]
    adjusted = dict(estimates)
    for kf_id, pose in poses.items():
        scale = _scale(by_id[kf_id].points3d, observed.own_rows[kf_id], pose, adjusted_points)
        if scale is not None:
            sim3 = pose.copy()
            sim3[:3, :3] *= scale
            adjusted[kf_id] = sim3
    _follow_neighbours(adjusted, estimates, poses, segment_of, weak)
    stats = GlobalBundleAdjustmentStats(
        len(poses), len(used), len(observed.point_index), observed.loop_observations, fused,
        float(np.median(before)), float(np.median(after)),
    )  # fmt: skip
    return AdjustedMap(adjusted, observed.keys, adjusted_points, stats, frozenset(weak))


def _thinned(kept: np.ndarray, seen: np.ndarray, budget: int) -> np.ndarray:
    """``kept`` with an evenly spaced share of its points only, as many as bring their observations
    within ``budget``: rows follow the keyframes' keypoint order, so even spacing spreads over each
    keyframe's image. Keeping each keyframe's most observed points instead measured worse (they
    crowd where views overlap: 44-keyframe loop, 0.0075 against 0.0053 m with every point)."""
    total = int(seen[kept].sum())
    if budget <= 0 or total <= budget:
        return kept
    rows = np.flatnonzero(kept)
    count = max(int(len(rows) * budget / total), 1)
    thinned = np.zeros_like(kept)
    thinned[rows[np.round(np.linspace(0, len(rows) - 1, count)).astype(np.int64)]] = True
    return thinned


def _weak_keyframes(keyframes: Mapping[int, Keyframe], share: float) -> set[int]:
    """Keyframes mapping fewer points than ``share`` x the median keyframe's. Where tracking
    degrades (before a loss: keyframes every few frames, 40-120 points each against ~700) the
    pixels tie such a stretch to the rest of the map only loosely, and adjusting it with the
    map moved it as a whole away from the well-mapped part: 3000-frame loop, seed 1, ATE
    0.047 -> 0.063 m, while the well-mapped keyframes improved (docs/2026-12-06-long-runs.md)."""
    if share <= 0 or not keyframes:
        return set()
    mapped = {k: int((np.asarray(kf.point_ids) >= 0).sum()) for k, kf in keyframes.items()}
    floor = share * float(np.median(list(mapped.values())))
    return {k for k, count in mapped.items() if count < floor}


def _follow_neighbours(
    adjusted: dict[int, np.ndarray],
    estimates: Mapping[int, np.ndarray],
    poses: Mapping[int, np.ndarray],
    segment_of: Mapping[int, int],
    followers: set[int],
) -> None:
    """Each of ``followers`` takes the correction (new Sim(3) x old inverse) of the adjusted
    keyframe of its segment nearest in id (creation order), as ORB-SLAM carries the global BA's
    correction to keyframes it did not adjust; without one in its segment it stays."""
    for segment in {segment_of[k] for k in followers}:
        anchors = np.array(sorted(k for k in poses if segment_of.get(k) == segment))
        if len(anchors) == 0:
            continue
        for kf_id in sorted(k for k in followers if segment_of[k] == segment):
            nearest = int(anchors[np.argmin(np.abs(anchors - kf_id))])
            correction = adjusted[nearest] @ np.linalg.inv(np.asarray(estimates[nearest], np.float64))
            adjusted[kf_id] = correction @ np.asarray(estimates[kf_id], np.float64)


def _solve(
    poses: Mapping[int, np.ndarray],
    positions: np.ndarray,
    observed: _Observations,
    camera: CameraIntrinsics,
    config: GlobalBundleAdjustmentConfig,
) -> tuple[dict[int, np.ndarray], np.ndarray] | None:
    """Levenberg-Marquardt from ``poses`` (SE(3)) and point ``positions``; None when it failed or
    found nothing better."""
    observed, ordering = _ordered_within_budget(observed, poses, config)
    keyframe_ids, point_index, sigmas = observed.keyframe_ids, observed.point_index, observed.sigma
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
                np.ascontiguousarray(observed.xy[level].T), noise_by_sigma[sigma], calibration,
            )  # fmt: skip
    _add_gauge(graph, poses)

    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(config.iterations)
    params.setRelativeErrorTol(config.relative_error_tolerance)
    params.setOrdering(ordering)
    # Nielsen's damping update: after a success, GTSAM's fixed factor cuts lambda tenfold and the
    # next step mostly fails, so every other linear solve was wasted.
    params.setUseFixedLambdaFactor(False)
    # Damping scaled by the Hessian's diagonal (Marquardt's): with GTSAM's default, identity-scaled
    # damping the first step on a many-keyframe map can put points behind cameras (infinite cost)
    # however large lambda grows (measured on a 110-keyframe synthetic map: no step accepted).
    params.setDiagonalDamping(True)
    # Near a minimum of the robust cost, steps succeed only heavily damped and gain < 0.5 % each
    # at 3-8 s apiece on a 600-keyframe map (docs/2026-12-07-global-ba-damping.md).
    params.setlambdaUpperBound(config.max_lambda)
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    try:
        result = optimizer.optimize()
    except RuntimeError as exc:  # e.g. an indeterminant system: the pose graph's answer stands
        log.warning("global bundle adjustment failed (%s); keeping the pose graph's estimates", exc)
        return None
    initial_error, final_error = graph.error(values), graph.error(result)
    log.info(
        "global bundle adjustment solve: %d factors, %d Levenberg-Marquardt iterations, error %.4g -> %.4g",
        graph.size(), optimizer.iterations(), initial_error, final_error,
    )  # fmt: skip
    if final_error >= initial_error:
        log.warning("global bundle adjustment found no better map; keeping the pose graph's estimates")
        return None
    adjusted = positions.copy()
    for index in used.tolist():
        adjusted[index] = result.atPoint3(index)
    return {k: result.atPose3(gtsam.symbol("x", k)).matrix() for k in poses}, adjusted


def _ordered_within_budget(
    observed: _Observations, poses: Mapping[int, np.ndarray], config: GlobalBundleAdjustmentConfig
) -> tuple[_Observations, gtsam.Ordering]:
    """The elimination ordering, and the observations to solve with: all of them, unless even the
    best ordering's largest clique gathers more than ``max_gather_mb``. Then the longest point
    tracks are thinned (``_capped_tracks``) until it fits. A point seen by k keyframes leaves a
    (6k)^2 block that its keyframes' clique holds with those of its other points, so the long
    tracks of a map revisited many times set the peak (docs/2026-12-07-global-ba-memory.md)."""
    budget = config.max_gather_mb * 1e6
    lengths = np.bincount(observed.point_index)
    kept, cap = observed, int(lengths.max(initial=0))
    ordering, gather = _least_gathering_ordering(kept.keyframe_ids, kept.point_index, poses)
    for _ in range(_BUDGET_ROUNDS):
        if budget <= 0 or gather <= budget or cap <= 2:
            break
        cap = _cap_for(lengths, cap, budget / gather)
        kept = observed.subset(_capped_tracks(observed.point_index, observed.keyframe_ids, cap))
        log.info(
            "global BA: largest clique %.0f MB > max_gather_mb %.0f; tracks capped at %d observations "
            "(%d of %d kept)", gather / 1e6, config.max_gather_mb, cap, len(kept.point_index),
            len(observed.point_index),
        )  # fmt: skip
        ordering, gather = _least_gathering_ordering(kept.keyframe_ids, kept.point_index, poses)
    return kept, ordering


#: Rounds of track thinning at most (each one ~1-3 s of symbolic work on a 200k-observation map).
_BUDGET_ROUNDS = 5


def _cap_for(lengths: np.ndarray, cap: int, ratio: float) -> int:
    """The largest cap below ``cap`` that shrinks sum(min(k, cap)^2) over the track lengths k by
    ``ratio`` (at least 2): the gathered blocks grow with the square of the tracks they come from,
    and which tracks a clique gathers is not known before the ordering, so all of them count."""
    caps = np.arange(2, max(cap, 3))
    k = np.sort(lengths).astype(np.float64)
    shorter = np.searchsorted(k, caps)  # tracks shorter than each cap keep their length
    below = np.r_[0.0, np.cumsum(k**2)]
    volumes = below[shorter] + caps.astype(np.float64) ** 2 * (len(k) - shorter)
    want = ratio * float((np.minimum(k, cap) ** 2).sum())
    fitting = np.flatnonzero(volumes <= want)
    return int(caps[fitting[-1]]) if len(fitting) else 2


def _capped_tracks(point_index: np.ndarray, keyframe_ids: np.ndarray, cap: int) -> np.ndarray:
    """Mask keeping at most ``cap`` observations of each point, evenly spaced over its observers in
    keyframe order, the first and the last kept: every pass over the place still ties in."""
    order = np.lexsort((keyframe_ids, point_index))
    points = point_index[order]
    starts = np.flatnonzero(np.r_[True, points[1:] != points[:-1]])
    counts = np.diff(np.r_[starts, len(points)])
    n = np.repeat(counts, counts)
    rank = np.arange(len(points)) - np.repeat(starts, counts)
    # Rank r is kept when r = round(j (n - 1) / (cap - 1)) for some j in 0..cap-1: the two j
    # nearest to r (cap - 1) / (n - 1) are the only ones that can give it.
    spacing = (n - 1.0) / (cap - 1)
    below = np.floor(rank / np.maximum(spacing, 1e-12) + 1e-9)
    hit = (np.round(below * spacing) == rank) | (np.round((below + 1) * spacing) == rank)
    keep = np.zeros(len(points), dtype=bool)
    keep[order[(n <= cap) | hit]] = True
    return keep


def _least_gathering_ordering(
    keyframe_ids: np.ndarray, point_index: np.ndarray, poses: Mapping[int, np.ndarray]
) -> tuple[gtsam.Ordering, float]:
    """METIS's or COLAMD's ordering of the observations' symbolic graph (one factor per
    keyframe-point pair, in keyframe order, plus the gauge priors), whichever has the smaller
    ``_largest_gather``, and that gather (bytes). The peak memory of GTSAM's multifrontal
    elimination followed the largest gather at ~250 MB above it on both long maps measured, and
    each of the two orderings lost by 0.4-0.9 GB on one of them. METIS's result also depends on
    the factors' order (621-1087 MB over seven orders of one figure-8 map); trying more orders
    cost 1.4 s each there and did not beat this one (docs/2026-12-07-global-ba-memory.md)."""
    pairs = np.unique(np.stack([keyframe_ids, point_index]), axis=1)
    symbolic = gtsam.SymbolicFactorGraph()
    for kf_id, point in pairs.T.tolist():
        symbolic.push_factor(gtsam.symbol("x", kf_id), point)
    for kf_id in poses:  # the gauge priors
        symbolic.push_factor(gtsam.symbol("x", kf_id))
    candidates = [
        gtsam.Ordering.MetisSymbolicFactorGraph(symbolic),
        gtsam.Ordering.ColamdSymbolicFactorGraph(symbolic),
    ]
    gathers = [_largest_gather(symbolic, ordering) for ordering in candidates]
    best = int(np.argmin(gathers))
    log.debug("global BA ordering: largest gather METIS %.0f MB, COLAMD %.0f MB", *(g / 1e6 for g in gathers))
    return candidates[best], gathers[best]


def _largest_gather(symbolic: gtsam.SymbolicFactorGraph, ordering: gtsam.Ordering) -> float:
    """Bytes of the largest set of dense blocks that eliminating one clique of ``ordering`` holds
    at once: its own (frontal + separator dimensions)^2 block and its children's separator^2
    update blocks (doubles; keyframe ``x`` keys 6 dimensions, point keys 3)."""
    first_pose_key = gtsam.symbol("x", 0)  # "x" keys lie above every point index
    tree = symbolic.eliminateMultifrontal(ordering)
    own: dict[int, float] = {}
    gathered: dict[int, float] = {}
    for i in range(ordering.size()):
        clique = tree[ordering.at(i)]
        conditional = clique.conditional()
        first = conditional.firstFrontalKey()
        if first in own:
            continue
        dims = np.where(np.asarray(conditional.keys(), dtype=np.uint64) >= first_pose_key, 6, 3)
        own[first] = 8.0 * float(dims.sum()) ** 2
        parent = clique.parent()
        if parent is not None:
            up = parent.conditional().firstFrontalKey()
            separator = float(dims[conditional.nrFrontals() :].sum())
            gathered[up] = gathered.get(up, 0.0) + 8.0 * separator**2
    return max(size + gathered.get(first, 0.0) for first, size in own.items())


def _fused_observations(
    keyframes: Mapping[int, Keyframe],
    poses: Mapping[int, np.ndarray],
    positions: np.ndarray,
    observed: _Observations,
    camera: CameraIntrinsics,
    config: GlobalBundleAdjustmentConfig,
) -> _Observations:
    """Observations of adjusted points by keyframes that do not observe them yet (ORB-SLAM's fusion
    of duplicated map points): every point is projected into every keyframe; it is observed at the
    keypoint within ``fuse_radius_px`` whose descriptor is nearest to the point's (that of its
    oldest observer), when nearer than ``fuse_max_hamming`` bits and no other point claims the
    keypoint with a nearer one. A map that drifted between two visits re-mapped what it saw
    before under new points; the loops' own correspondences tie a few keyframe pairs, this ties
    every keyframe to every point it sees."""
    rows = np.unique(observed.point_index)
    owner = np.full(len(observed.keys), -1, np.int64)  # oldest observer and its keypoint, per row
    owner_keypoint = np.full(len(observed.keys), -1, np.int64)
    for kf_id in sorted(keyframes, reverse=True):
        own = observed.own_rows[kf_id]
        if len(keyframes[kf_id].descriptors) != len(own):
            continue
        mapped = np.flatnonzero(own >= 0)
        owner[own[mapped]], owner_keypoint[own[mapped]] = kf_id, mapped
    rows = rows[owner[rows] >= 0]
    fused = observed.subset(np.zeros(len(observed.point_index), bool))
    if len(rows) == 0:
        return fused
    descriptors = np.stack([keyframes[int(owner[r])].descriptors[owner_keypoint[r]] for r in rows.tolist()])
    for kf_id, pose in poses.items():
        keyframe = keyframes[kf_id]
        if len(keyframe.keypoints) == 0 or len(keyframe.descriptors) != len(keyframe.keypoints):
            continue
        seen = np.zeros(len(observed.keys), bool)
        seen[observed.point_index[observed.keyframe_ids == kf_id]] = True
        candidates = np.flatnonzero(~seen[rows])
        uv, visible = _pixels(pose, positions[rows[candidates]], camera)
        candidates, uv = candidates[visible], uv[visible]
        keypoints = camera.undistort(keyframe.keypoints)
        near = cKDTree(keypoints).query_ball_point(uv, config.fuse_radius_px)
        counts = np.array([len(n) for n in near], np.int64)
        if counts.sum() == 0:
            continue
        which = np.repeat(candidates, counts)
        keypoint = np.concatenate([np.asarray(n, np.int64) for n in near if n])
        bits = np.unpackbits(descriptors[which] ^ keyframe.descriptors[keypoint], axis=1).sum(axis=1)
        close = bits < config.fuse_max_hamming
        which, keypoint, bits = which[close], keypoint[close], bits[close]
        # Each point its nearest keypoint (by descriptor), then each keypoint its nearest point.
        best = _nearest_per(which, bits)
        which, keypoint, bits = which[best], keypoint[best], bits[best]
        best = _nearest_per(keypoint, bits)
        which, keypoint = which[best], keypoint[best]
        fused = fused.joined(
            replace(
                fused, keyframe_ids=np.full(len(which), kf_id, np.int64), xy=keypoints[keypoint],
                point_index=rows[which], sigma=_keypoint_sigmas(keyframe)[keypoint],
            )
        )  # fmt: skip
    return fused


def _nearest_per(group: np.ndarray, distance: np.ndarray) -> np.ndarray:
    """Index of the smallest ``distance`` of each value of ``group``."""
    order = np.lexsort((distance, group))
    return order[np.unique(group[order], return_index=True)[1]]


def _pixels(pose: np.ndarray, points: np.ndarray, camera: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted pixels of world points in a camera-to-world SE(3) pose, and which are in front
    of the camera and inside the image."""
    in_camera = (points - pose[:3, 3]) @ pose[:3, :3]
    in_front = in_camera[:, 2] > 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = in_camera[:, :2] / in_camera[:, 2:] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    inside = in_front & (uv >= 0).all(axis=1) & (uv[:, 0] < camera.width) & (uv[:, 1] < camera.height)
    return uv, inside


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

    def subset(self, mask: np.ndarray) -> _Observations:
        return replace(
            self, keyframe_ids=self.keyframe_ids[mask], xy=self.xy[mask], point_index=self.point_index[mask],
            sigma=self.sigma[mask],
        )  # fmt: skip

    def joined(self, other: _Observations) -> _Observations:
        """These observations and ``other``'s (of the same points)."""
        return replace(
            self,
            keyframe_ids=np.concatenate([self.keyframe_ids, other.keyframe_ids]),
            xy=np.concatenate([self.xy, other.xy]),
            point_index=np.concatenate([self.point_index, other.point_index]),
            sigma=np.concatenate([self.sigma, other.sigma]),
        )


def _keypoint_sigmas(keyframe: Keyframe) -> np.ndarray:
    sigmas = keyframe.keypoint_sigmas
    return np.ones(len(keyframe.keypoints)) if sigmas is None else np.asarray(sigmas, np.float64)


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
        rows_sigma.append(_keypoint_sigmas(observer)[keypoints[mapped]])
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


def _add_gauge(graph: gtsam.NonlinearFactorGraph, poses: Mapping[int, np.ndarray]) -> None:
    """A weak prior on every keyframe at its start (sigma 1 rad and one median keyframe step):
    it fixes the map's similarity gauge, which the pixels leave free, where the map started, and
    is otherwise negligible beside the pixels. Holding the oldest keyframe and one distance with
    1e-6 sigmas instead stiffened the system so much that Levenberg-Marquardt stopped in a flat
    valley short of the optimum (figure8 seed 0: keyframe ATE 8.3 mm, and 7.4 mm after 100
    iterations, against 4.5 mm in 3 iterations with this prior at the same final error)."""
    ids = sorted(poses)
    centres = np.array([poses[k][:3, 3] for k in ids])
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    step = float(np.median(steps)) if len(steps) and np.median(steps) > 0 else 1.0
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([1.0] * 3 + [step] * 3))
    for kf_id in ids:
        graph.add(gtsam.PriorFactorPose3(gtsam.symbol("x", kf_id), gtsam.Pose3(poses[kf_id]), noise))


def _reprojection_errors(
    poses: Mapping[int, np.ndarray], points: np.ndarray, observed: _Observations, camera: CameraIntrinsics
) -> np.ndarray:
    """Pixel error of every observation (undistorted pixels, camera-to-world poses)."""
    ids = np.array(sorted(poses))
    stacked = np.stack([poses[k] for k in ids.tolist()])
    which = np.searchsorted(ids, observed.keyframe_ids)
    rotation, center = stacked[which, :3, :3], stacked[which, :3, 3]
    in_camera = np.einsum("nji,nj->ni", rotation, points[observed.point_index] - center)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = in_camera[:, :2] / in_camera[:, 2:] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    return np.nan_to_num(np.linalg.norm(uv - observed.xy, axis=1), nan=np.inf)


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
