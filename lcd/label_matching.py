"""SymbioLCD's object comparison in a scale-invariant normalised plane (Kim et al., 2021).

Each keyframe's object centres are moved to their centroid and divided by their RMS distance from
it, so the layout no longer depends on scale or where it sits in the image. Objects of two
keyframes are then matched one-to-one, only label to label, by minimum total normalised distance
(Hungarian assignment), and a match farther than ``max_distance`` is refused. The match ratio is
matched / objects of the larger set: the paper tolerates up to 40 % missing or misclassified
labels, so keyframes "agree" when the ratio is at least 0.6. The modified Hausdorff distance
between the two normalised layouts is SymbioLCD's second spatial feature.

Our interpretation: with fewer than two objects the plane is undefined; such a pair gets ratio
from labels alone (1 when the single labels agree) and an infinite Hausdorff distance.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from frontends.types import DetectedObject


@dataclass(frozen=True)
class LabelMatchConfig:
    #: Largest normalised distance at which two same-label objects still match.
    max_distance: float = 0.75
    #: Share of objects that must match for the keyframes to agree (0.6: 40 % may be missing).
    min_ratio: float = 0.6


@dataclass(frozen=True)
class LabelMatch:
    ratio: float
    #: (index in a, index in b) of the matched objects.
    pairs: tuple[tuple[int, int], ...]
    hausdorff: float

    def agrees(self, config: LabelMatchConfig) -> bool:
        return self.ratio >= config.min_ratio


def normalised_centres(objects: Sequence[DetectedObject]) -> np.ndarray:
    """Box centres, centred on their centroid and scaled to unit RMS radius."""
    if not objects:
        return np.zeros((0, 2))
    boxes = np.array([o.box for o in objects], dtype=np.float64)
    centres = np.column_stack([(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2])
    centres -= centres.mean(axis=0)
    radius = float(np.sqrt((centres**2).sum(axis=1).mean()))
    return centres / radius if radius > 0 else centres


def modified_hausdorff(a: np.ndarray, b: np.ndarray) -> float:
    """Dubuisson and Jain's modified Hausdorff distance (robust to one outlying point)."""
    if len(a) == 0 or len(b) == 0:
        return float("inf")
    distances = cdist(a, b)
    return float(max(distances.min(axis=1).mean(), distances.min(axis=0).mean()))


def match_labels(
    a: Sequence[DetectedObject], b: Sequence[DetectedObject], config: LabelMatchConfig = LabelMatchConfig()
) -> LabelMatch:
    if not a or not b:
        return LabelMatch(0.0, (), float("inf"))
    pa, pb = normalised_centres(a), normalised_centres(b)
    hausdorff = modified_hausdorff(pa, pb) if len(a) >= 2 and len(b) >= 2 else float("inf")
    same_label = np.array([[oa.label == ob.label for ob in b] for oa in a])
    if len(a) < 2 or len(b) < 2:
        # No plane to compare in: labels alone decide.
        pairs = _label_only_pairs(same_label)
    else:
        cost = cdist(pa, pb)
        forbidden = ~same_label | (cost > config.max_distance)
        # A large finite cost keeps the assignment feasible; such pairs are dropped afterwards.
        rows, cols = linear_sum_assignment(np.where(forbidden, 1e6, cost))
        pairs = [(int(r), int(c)) for r, c in zip(rows, cols, strict=True) if not forbidden[r, c]]
    return LabelMatch(len(pairs) / max(len(a), len(b)), tuple(pairs), hausdorff)


def _label_only_pairs(same_label: np.ndarray) -> list[tuple[int, int]]:
    used: set[int] = set()
    pairs = []
    for row in range(same_label.shape[0]):
        for col in np.flatnonzero(same_label[row]):
            if int(col) not in used:
                used.add(int(col))
                pairs.append((row, int(col)))
                break
    return pairs
