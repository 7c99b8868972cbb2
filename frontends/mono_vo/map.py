"""The map of one segment: map points in growable numpy arrays, and the keyframes that observe them.

Observations live on the keyframes (``KeyframeState.point_ids``: the map point of each keypoint,
-1 for none), so every query the tracker and bundle adjustment make is a vectorised gather over a
few keyframes rather than a walk over per-point Python objects. Per point the store keeps position,
descriptor (the newest observation's: appearance drifts with the viewpoint), the number of keyframes
observing it, and ORB-SLAM's visible/found counters for culling points that are predicted in view
but rarely matched.

For the tracker's projection search each point also keeps ORB-SLAM's viewing statistics: the mean
viewing direction (unit rays from the observing keyframes), the descriptor keypoint's angle, and the
distance range over which its descriptor patch stays within the pyramid (``max_distance`` = distance
x scale factor^octave when observed, ``min_distance`` = that / scale factor^(levels-1)). A point
seen from far outside that range or from another side (a background point behind an occluder seen
from a new angle) would show a different patch, so it is not searched for.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from frontends.mono_vo.features import Features
from frontends.mono_vo.geometry import invert
from frontends.types import Keyframe


@dataclass
class KeyframeState:
    """A keyframe as the frontend works with it."""

    id: int
    frame_index: int
    timestamp: float
    #: World-to-camera pose (bundle adjusted).
    T_cw: np.ndarray
    features: Features
    #: (N,) map point of each keypoint, -1 where none.
    point_ids: np.ndarray
    #: What the API hands out (pose and points3d refreshed from T_cw and the map).
    output: Keyframe
    #: (N,) keypoints on objects that move on their own (DynaSLAM's masks): never mapped.
    dynamic: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    #: How much loop corrections have scaled the map around this keyframe since it was made (its
    #: backend node's scale; a new keyframe starts with its predecessor's). The output pose carries
    #: it as a Sim(3) and the output points3d are divided by it, so both stay in the units the
    #: keyframe's odometry step and loop constraints were measured in.
    scale: float = 1.0
    #: Points of older covisible keyframes that the tracking window lacks and this keyframe has in
    #: view (``SegmentMap.link_covisible``); they join the local map while this one is the newest.
    covisible_points: np.ndarray | None = None


@dataclass
class PointStore:
    """Map points of one segment; ids index the arrays and are never reused."""

    positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    descriptors: np.ndarray = field(default_factory=lambda: np.zeros((0, 32), np.uint8))
    observations: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    visible: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    found: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    first_keyframe: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    alive: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    #: Mean viewing direction (unit), descriptor angle (deg), scale-invariance distance range.
    normals: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    angles: np.ndarray = field(default_factory=lambda: np.zeros(0))
    min_distance: np.ndarray = field(default_factory=lambda: np.zeros(0))
    max_distance: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        return len(self.positions)

    def add(self, positions: np.ndarray, keyframe_id: int) -> np.ndarray:
        """Append points without observations (``SegmentMap.observe`` fills in the rest); their ids."""
        count = len(positions)
        ids = np.arange(len(self), len(self) + count)
        self.positions = np.concatenate([self.positions, positions])
        self.descriptors = np.concatenate([self.descriptors, np.zeros((count, 32), np.uint8)])
        self.observations = np.concatenate([self.observations, np.zeros(count, np.int64)])
        self.visible = np.concatenate([self.visible, np.ones(count, np.int64)])
        self.found = np.concatenate([self.found, np.ones(count, np.int64)])
        self.first_keyframe = np.concatenate([self.first_keyframe, np.full(count, keyframe_id)])
        self.alive = np.concatenate([self.alive, np.ones(count, bool)])
        self.normals = np.concatenate([self.normals, np.zeros((count, 3))])
        self.angles = np.concatenate([self.angles, np.zeros(count)])
        self.min_distance = np.concatenate([self.min_distance, np.zeros(count)])
        self.max_distance = np.concatenate([self.max_distance, np.zeros(count)])
        return ids


class SegmentMap:
    """Keyframes and map points of one map segment."""

    def __init__(self, segment: int, octave_scale: np.ndarray) -> None:
        self.segment = segment
        #: Scale factor of each pyramid level (1, 1.2, 1.44, ...).
        self.octave_scale = octave_scale
        self.points = PointStore()
        self.keyframes: list[KeyframeState] = []

    def live_ids(self, keyframe: KeyframeState) -> np.ndarray:
        """The keyframe's point ids with dead points replaced by -1 (kept in place)."""
        ids = keyframe.point_ids
        valid = ids >= 0
        valid[valid] = self.points.alive[ids[valid]]
        ids[~valid] = -1
        return ids

    def shared_points(self, first: KeyframeState, second: KeyframeState) -> int:
        """How many alive map points both keyframes observe (ORB-SLAM's covisibility weight)."""
        a, b = self.live_ids(first), self.live_ids(second)
        return len(np.intersect1d(a[a >= 0], b[b >= 0]))

    def local_point_ids(self, count: int) -> np.ndarray:
        """Alive points observed by the last ``count`` keyframes, and the newest one's points from
        covisible keyframes (``link_covisible``)."""
        window = self.keyframes[-count:]
        if not window:
            return np.zeros(0, np.int64)
        extra = window[-1].covisible_points
        parts = [self.live_ids(kf) for kf in window]
        if extra is not None and len(extra):
            parts.append(extra[self.points.alive[extra]])
        ids = np.unique(np.concatenate(parts))
        return ids[ids >= 0]

    def link_covisible(
        self,
        keyframe: KeyframeState,
        window: int,
        reach: int,
        count: int,
        min_shared: int,
        in_view: Callable[[np.ndarray], np.ndarray],
    ) -> None:
        """Give ``keyframe`` (the newest) the points of its covisible keyframes that the tracking
        window lacks: among the ``reach`` keyframes before it, those older than the last ``window``
        that share at least ``min_shared`` alive points with it, the ``count`` with the most such
        points ``in_view`` (a mask over point ids: in the keyframe's view), newest first on a tie.
        While something hides part of the view, keyframes come every frame or two and the window
        forgets the hidden points; these bring them back when the view clears, as ORB-SLAM's
        covisible local map does (docs/2026-12-07-slow-camera.md)."""
        keyframe.covisible_points = None
        older = self.keyframes[max(0, len(self.keyframes) - 1 - reach) : max(0, len(self.keyframes) - window)]
        if count <= 0 or not older:
            return
        own = self.live_ids(keyframe)
        own = own[own >= 0]
        if len(own) < min_shared:
            return
        known = np.concatenate([self.live_ids(kf) for kf in self.keyframes[-window:]])
        extras: list[np.ndarray] = []
        for other in reversed(older):
            ids = self.live_ids(other)
            ids = ids[ids >= 0]
            if np.count_nonzero(np.isin(ids, own)) < min_shared:
                continue
            ids = ids[~np.isin(ids, known)]
            extras.append(ids[in_view(ids)] if len(ids) else ids)
        best = np.argsort([-len(e) for e in extras], kind="stable")[:count]
        chosen = [extras[i] for i in best if len(extras[i])]
        if chosen:
            keyframe.covisible_points = np.unique(np.concatenate(chosen))

    def observe(
        self, keyframe: KeyframeState, keypoint_idx: np.ndarray, point_ids: np.ndarray, newest: bool = True
    ) -> None:
        """Record that the keyframe sees ``point_ids`` at ``keypoint_idx``; every observation joins
        the mean viewing direction, the newest one (``newest``) also gives the descriptor, its angle
        and distance range."""
        p = self.points
        keyframe.point_ids[keypoint_idx] = point_ids
        ray = p.positions[point_ids] - invert(keyframe.T_cw)[:3, 3]
        distance = np.maximum(np.linalg.norm(ray, axis=1), 1e-12)
        normal = p.normals[point_ids] * p.observations[point_ids, None] + ray / distance[:, None]
        p.normals[point_ids] = normal / np.maximum(np.linalg.norm(normal, axis=1), 1e-12)[:, None]
        p.observations[point_ids] += 1
        if not newest:
            return
        p.descriptors[point_ids] = keyframe.features.descriptors[keypoint_idx]
        p.angles[point_ids] = keyframe.features.angles[keypoint_idx]
        octave = np.minimum(keyframe.features.octaves[keypoint_idx], len(self.octave_scale) - 1)
        p.max_distance[point_ids] = distance * self.octave_scale[octave]
        p.min_distance[point_ids] = p.max_distance[point_ids] / self.octave_scale[-1]

    def drop_observations(self, keyframe: KeyframeState, keypoint_idx: np.ndarray) -> None:
        ids = keyframe.point_ids[keypoint_idx]
        ids = ids[ids >= 0]
        np.subtract.at(self.points.observations, ids, 1)
        keyframe.point_ids[keypoint_idx] = -1

    def fuse(self, first: np.ndarray, second: np.ndarray) -> int:
        """Merge pairs of alive points that are the same scene point (ORB-SLAM's Fuse): the one
        with more observations (the older on a tie) takes over the other's observations, its
        visible/found counts and a share of its mean viewing direction; the other dies. A keyframe
        that observed both keeps the survivor's own observation. Returns how many points died."""
        p = self.points
        valid = (first != second) & p.alive[first] & p.alive[second]
        first, second = first[valid], second[valid]
        if len(first) == 0:
            return 0
        first_wins = (p.observations[first] > p.observations[second]) | (
            (p.observations[first] == p.observations[second]) & (first < second)
        )
        remap = np.arange(len(p))
        remap[np.where(first_wins, second, first)] = np.where(first_wins, first, second)
        # Chains (a -> b, b -> c) follow to their end; every step goes up one total order, so none loops.
        while not np.array_equal(remap[remap], remap):
            remap = remap[remap]
        dropped = np.flatnonzero(remap != np.arange(len(p)))
        kept = remap[dropped]
        weight_kept, weight_dropped = p.observations[kept, None], p.observations[dropped, None]
        normal = p.normals[kept] * weight_kept + p.normals[dropped] * weight_dropped
        p.normals[kept] = normal / np.maximum(np.linalg.norm(normal, axis=1), 1e-12)[:, None]
        for counter in (p.observations, p.visible, p.found):
            np.add.at(counter, kept, counter[dropped])
        p.observations[dropped] = 0
        p.alive[dropped] = False
        for kf in self.keyframes:
            ids = kf.point_ids
            moved = np.flatnonzero(ids >= 0)
            moved = moved[remap[ids[moved]] != ids[moved]]
            if len(moved) == 0:
                continue
            ids[moved] = remap[ids[moved]]
            # Where the keyframe now holds a point twice, the observation that was already its own stays.
            own_first = np.ones(len(ids), bool)
            own_first[moved] = False
            order = np.lexsort((~own_first, ids))
            sorted_ids = ids[order]
            repeat = order[1:][(sorted_ids[1:] == sorted_ids[:-1]) & (sorted_ids[1:] >= 0)]
            np.subtract.at(p.observations, ids[repeat], 1)
            ids[repeat] = -1
        return len(dropped)

    def cull(self, current_keyframe_id: int, min_found_ratio: float = 0.25) -> int:
        """ORB-SLAM's culling rules: rarely matched when visible (here for points of any age, where
        ORB-SLAM checks only recent ones; limiting it to recent points measured neutral, docs/slam-runs.md,
        "Measured and not adopted"), or
        seen by <= 2 keyframes two keyframes after their creation. Returns how many points died."""
        p = self.points
        age = current_keyframe_id - p.first_keyframe
        rarely_found = (p.visible >= 10) & (p.found < min_found_ratio * p.visible)
        unconfirmed = (age >= 2) & (p.observations <= 2)
        dead = p.alive & (rarely_found | unconfirmed | (p.observations < 1))
        p.alive &= ~dead
        return int(dead.sum())
