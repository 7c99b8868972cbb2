"""A pose-graph problem: odometry chain, loop candidates in arrival order, optional ground truth.

Both the dataset importers (:mod:`slam_backend.graph_io`) and the monocular simulation
(:mod:`slam_backend.simulate`) produce one; :mod:`slam_backend.experiment` feeds it to a backend.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from slam_backend.lie import Mode


@dataclass(frozen=True)
class LoopCandidate:
    #: Keyframe ids, ``relative ~ pose(start)^-1 * pose(end)``; the loop arrives with the later keyframe.
    start: int
    end: int
    relative: np.ndarray
    covariance: np.ndarray
    #: Ground-truth label: a real revisit (True) or an injected false loop (False).
    is_true: bool


@dataclass
class PoseGraphProblem:
    name: str
    mode: Mode
    keyframe_ids: list[int]
    #: ``odometry[0]`` is the first keyframe's initial pose; ``odometry[k]`` goes from keyframe k-1 to k.
    odometry: list[np.ndarray]
    odometry_covariances: list[np.ndarray]
    loops: list[LoopCandidate] = field(default_factory=list)
    #: Ground-truth camera-to-world 4x4 poses of the keyframes (SE(2) lifted to z=0), if known.
    gt_poses: np.ndarray | None = None
    #: Keyframe timestamps (s), or keyframe indices when the source has no time.
    timestamps: np.ndarray | None = None

    @property
    def loops_true(self) -> int:
        return sum(loop.is_true for loop in self.loops)

    @property
    def loops_false(self) -> int:
        return sum(not loop.is_true for loop in self.loops)

    def dead_reckoning(self) -> list[np.ndarray]:
        """Poses from composing the odometry alone (homogeneous matrices of the problem's group)."""
        poses = [self.odometry[0]]
        for step in self.odometry[1:]:
            poses.append(poses[-1] @ step)
        return poses

    def arrival_order(self) -> list[list[LoopCandidate]]:
        """For each keyframe position, the loops that arrive with it (in candidate order)."""
        position = {key: n for n, key in enumerate(self.keyframe_ids)}
        arrivals: list[list[LoopCandidate]] = [[] for _ in self.keyframe_ids]
        for loop in self.loops:
            arrivals[max(position[loop.start], position[loop.end])].append(loop)
        return arrivals

    def truncated(self, count: int) -> PoseGraphProblem:
        """The first ``count`` keyframes and the loops among them."""
        kept = set(self.keyframe_ids[:count])
        return dataclasses.replace(
            self,
            keyframe_ids=self.keyframe_ids[:count],
            odometry=self.odometry[:count],
            odometry_covariances=self.odometry_covariances[:count],
            loops=[loop for loop in self.loops if loop.start in kept and loop.end in kept],
            gt_poses=None if self.gt_poses is None else self.gt_poses[:count],
            timestamps=None if self.timestamps is None else self.timestamps[:count],
        )
