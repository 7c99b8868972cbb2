"""Pairwise consistency maximisation (PCM, Mangelson et al. 2018), incremental, for Sim(3)/SE(3)/SE(2).

Two loops ``a = (i, j, Z_a)`` and ``b = (k, l, Z_b)`` (``Z ~ X_i^-1 X_j``) are consistent when the
cycle ``C = Z_a^-1 * O(i->k) * Z_b * O(l->j)`` is close to the identity, where ``O`` is the
dead-reckoned odometry between two keyframes. "Close" is the squared Mahalanobis norm of
``Log(C)`` below the chi-square quantile ``chi2.ppf(confidence, dim)``.

Covariance of ``O(a->b)``: first-order propagation of every odometry step's covariance through the
chain. With ``X_n`` the dead-reckoned pose after step ``n``, a right perturbation ``e_n`` of step ``n``
moves ``X_n`` on the left by ``Ad(X_n) e_n``, so the prefix sums ``P_n = sum_k Ad(X_k) S_k Ad(X_k)^T``
give ``cov O(a->b) = Ad(X_b^-1) (P_b - P_a) Ad(X_b^-1)^T`` in O(1) per pair. Scale drift is part of
``S_k`` in Sim(3) mode, so a long chain between far-apart loops gets the (large) covariance it
deserves instead of being trusted. The four factors of the cycle are treated as independent; when
the two odometry segments overlap (loops far apart in time) the shared part is counted twice,
which only makes the test more permissive for such pairs (approximate, conservative).

Which pairs are tested: each new loop against the ``max_checks`` existing loops nearest to it in
time (``|i - k| + |j - l|``; all of them when there are fewer), so the cost of an event is bounded
whatever the number of loops. Pairs never tested count as consistent; what is stored is the
*conflict* graph (networkx; an edge = a tested pair that failed), the complement of PCM's
consistency graph, and the maximum consistent set is a maximum independent set of it.

Incremental update of the accepted set ``A`` when loop ``v`` arrives:

* ``v`` conflicts with no loop of ``A``: ``A + v`` (exact: a maximum set grows by at most one).
* otherwise a one-step exchange: ``A' = A - C + v + F`` where ``C`` are the accepted loops ``v``
  conflicts with and ``F`` a greedy (fewest conflicts first) independent set of the rejected loops
  that conflict with nothing in ``A - C + v``; ``A'`` replaces ``A`` only when strictly larger.
  Exact in the common cases (a false loop against a consistent set; a run of true loops taking
  over from an early false one), a bounded-cost approximation of the maximum clique otherwise.

Removing an accepted loop re-admits, greedily, the rejected loops it alone was blocking.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import networkx as nx
import numpy as np
from scipy.stats import chi2

from slam_backend.lie import PoseGroup


class OdometryChain:
    """Dead-reckoned poses and prefix-summed covariances of the odometry chain."""

    def __init__(self, group: PoseGroup) -> None:
        self.group = group
        self._poses: list[Any] = []
        self._prefix: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._poses)

    def append(self, step: Any, covariance: np.ndarray) -> None:
        """Add the next keyframe; ``step`` is the odometry from the previous one (ignored for the first)."""
        if not self._poses:
            self._poses.append(self.group.identity())
            self._prefix.append(np.zeros((self.group.dim, self.group.dim)))
            return
        pose = self._poses[-1].compose(step)
        adjoint = self.group.adjoint(pose)
        self._poses.append(pose)
        self._prefix.append(self._prefix[-1] + adjoint @ covariance @ adjoint.T)

    def pose(self, index: int) -> Any:
        return self._poses[index]

    def relative(self, start: int, end: int) -> tuple[Any, np.ndarray]:
        """``O(start->end) = X_start^-1 X_end`` and its covariance (right-perturbation convention)."""
        if start <= end:
            value = self._poses[start].between(self._poses[end])
            to_local = self.group.adjoint(self._poses[end].inverse())
            return value, to_local @ (self._prefix[end] - self._prefix[start]) @ to_local.T
        value, covariance = self.relative(end, start)
        flip = self.group.adjoint(value)
        return value.inverse(), flip @ covariance @ flip.T


@dataclass(frozen=True)
class LoopMeasurement:
    """A loop as PCM sees it: chain indices, the measured ``X_i^-1 X_j`` and its covariance."""

    start: int
    end: int
    value: Any
    covariance: np.ndarray


class PairwiseConsistency:
    """Incremental PCM over loop ids; ``accepted`` is the current maximum consistent set."""

    def __init__(self, chain: OdometryChain, confidence: float, max_checks: int) -> None:
        self.chain = chain
        self.group = chain.group
        self.threshold = float(chi2.ppf(confidence, self.group.dim))
        self.max_checks = max_checks
        self.conflicts = nx.Graph()
        self._loops: dict[int, LoopMeasurement] = {}
        self.accepted: frozenset[int] = frozenset()
        self.tested_pairs = 0

    def __len__(self) -> int:
        return len(self._loops)

    def __contains__(self, loop_id: object) -> bool:
        return loop_id in self._loops

    def _compose(
        self, first: tuple[Any, np.ndarray], second: tuple[Any, np.ndarray]
    ) -> tuple[Any, np.ndarray]:
        transport = self.group.adjoint(second[0].inverse())
        return first[0].compose(second[0]), transport @ first[1] @ transport.T + second[1]

    def mahalanobis(self, a: LoopMeasurement, b: LoopMeasurement) -> float:
        """Squared Mahalanobis norm of the cycle ``Z_a^-1 O(i->k) Z_b O(l->j)``."""
        flip = self.group.adjoint(a.value)
        cycle = (a.value.inverse(), flip @ a.covariance @ flip.T)
        cycle = self._compose(cycle, self.chain.relative(a.start, b.start))
        cycle = self._compose(cycle, (b.value, b.covariance))
        value, covariance = self._compose(cycle, self.chain.relative(b.end, a.end))
        residual = self.group.logmap(value)
        return float(residual @ np.linalg.solve(covariance, residual))

    def conflict_count(self, loop_id: int) -> int:
        return int(self.conflicts.degree[loop_id])

    def _nearest(self, loop: LoopMeasurement) -> list[int]:
        ids = list(self._loops)
        if len(ids) <= self.max_checks:
            return ids
        starts = np.array([self._loops[i].start for i in ids])
        ends = np.array([self._loops[i].end for i in ids])
        distance = np.abs(starts - loop.start) + np.abs(ends - loop.end)
        return [ids[n] for n in np.argsort(distance, kind="stable")[: self.max_checks]]

    def add(self, loop_id: int, loop: LoopMeasurement) -> frozenset[int]:
        """Add a loop, update the maximum consistent set and return it."""
        self.conflicts.add_node(loop_id)
        for other_id in self._nearest(loop):
            self.tested_pairs += 1
            if self.mahalanobis(loop, self._loops[other_id]) >= self.threshold:
                self.conflicts.add_edge(loop_id, other_id)
        self._loops[loop_id] = loop
        blocking = self.accepted & set(self.conflicts.neighbors(loop_id))
        if not blocking:
            self.accepted = self.accepted | {loop_id}
            return self.accepted
        kept = (self.accepted - blocking) | {loop_id}
        candidate = kept | self._admissible(kept)
        if len(candidate) > len(self.accepted):
            self.accepted = frozenset(candidate)
        return self.accepted

    def _admissible(self, kept: frozenset[int] | set[int]) -> set[int]:
        """A greedy independent set of the loops outside ``kept`` that conflict with nothing in it."""
        free = [
            n
            for n in self.conflicts.nodes
            if n not in kept and not any(m in kept for m in self.conflicts.neighbors(n))
        ]
        chosen: set[int] = set()
        for node in sorted(free, key=lambda n: (self.conflicts.degree[n], n)):
            if not any(m in chosen for m in self.conflicts.neighbors(node)):
                chosen.add(node)
        return chosen

    def remove(self, loop_id: int) -> frozenset[int]:
        self.conflicts.remove_node(loop_id)
        del self._loops[loop_id]
        if loop_id in self.accepted:
            kept = self.accepted - {loop_id}
            self.accepted = frozenset(kept | self._admissible(kept))
        return self.accepted
