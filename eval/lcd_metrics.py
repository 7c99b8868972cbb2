"""Loop-closure detection metrics: pure numpy, no I/O (the evo-style core of ``symbio eval lcd``).

Protocol: every keyframe is a query against the keyframes before it (outside the detector's
temporal window); it yields its best candidate and that candidate's score. The candidate is a true
positive when it lies within ``tolerance`` frames of a ground-truth reference of the query. A query
"has a loop" when some earlier keyframe lies within ``tolerance`` frames of one of its references,
i.e. when a true positive was possible. Sweeping a threshold over the best scores gives the
precision/recall curve; recall = TP / queries that have a loop. ``recall_at_1``: the share of the
queries with a loop whose best candidate is right, whatever its score (place recognition's figure).

Verified protocol (``symbio eval lcd --verify``): each query's top-k candidates go, best first,
through the pipeline's two-view verification; the query's verified answer is the best-ranked
candidate that passes, kept with its inlier count. At the verifier's own decision every query with
a verified answer is accepted: ``precision_verified`` (1.0 when nothing is accepted, the raw
``precision``'s convention: no accepted loop, no false one) and ``recall_verified``, which is also
``recall_at_1_verified`` (no threshold sits between a verified answer and its acceptance).
``recall_at_100p_verified`` sweeps a threshold over the verified answers' inlier counts, not the
detector's scores: the inlier count is the verifier's own confidence, so a wrong place that
scraped through with few inliers is what a stricter threshold removes first.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from evo.core.lie_algebra import so3_log_angle

from slam_backend.lie import as_4x4


def gt_references(pairs: np.ndarray) -> dict[int, np.ndarray]:
    """Query frame -> sorted reference frames, from (query, ref) pairs."""
    # Views into one sorted array: a 9000-frame scene has 2.2 M pairs, which as Python lists took
    # 345 MB at the end of a run (docs/2026-12-06-long-runs.md).
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    ordered = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    queries, starts = np.unique(ordered[:, 0], return_index=True)
    refs = np.ascontiguousarray(ordered[:, 1])
    ends = np.append(starts[1:], len(refs))[: len(starts)]
    return {q: refs[a:b] for q, a, b in zip(queries.tolist(), starts.tolist(), ends.tolist(), strict=True)}


def is_true_match(match: int, references: np.ndarray | None, tolerance: int) -> bool:
    return references is not None and bool(np.any(np.abs(references - match) <= tolerance))


def has_reachable_loop(references: np.ndarray | None, candidates: Sequence[int], tolerance: int) -> bool:
    """Whether any keyframe frame in ``candidates`` lies within ``tolerance`` of a reference."""
    if references is None or len(candidates) == 0:
        return False
    frames = np.asarray(candidates, dtype=np.int64)
    return bool(np.any(np.abs(frames[:, None] - references[None, :]) <= tolerance))


def precision_recall_curve(
    scores: np.ndarray, correct: np.ndarray, positives: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(thresholds descending, precision, recall) accepting every best candidate with score >= threshold."""
    scores = np.asarray(scores, dtype=np.float64)
    correct = np.asarray(correct, dtype=bool)
    order = np.argsort(-scores, kind="stable")
    scores, correct = scores[order], correct[order]
    true_positives = np.cumsum(correct)
    accepted = np.arange(1, len(scores) + 1)
    # Tied scores are accepted together: keep the last index of each run of equal scores.
    last_of_tie = np.r_[scores[1:] != scores[:-1], True] if len(scores) else np.zeros(0, dtype=bool)
    precision = true_positives[last_of_tie] / accepted[last_of_tie]
    recall = true_positives[last_of_tie] / positives if positives else np.zeros(int(last_of_tie.sum()))
    return scores[last_of_tie], precision, recall


def summarise(
    scores: np.ndarray, correct: np.ndarray, positives: int, threshold: float
) -> Mapping[str, float | int]:
    """precision/recall at ``threshold``, recall at 100 % precision, and the area under the PR curve."""
    scores = np.asarray(scores, dtype=np.float64)
    correct = np.asarray(correct, dtype=bool)
    thresholds, precision, recall = precision_recall_curve(scores, correct, positives)
    accepted = scores >= threshold
    tp = int((accepted & correct).sum())
    perfect = precision >= 1.0
    # Average precision: each recall step weighted by the precision reached there.
    auc = float(np.sum(np.diff(np.r_[0.0, recall]) * precision)) if len(recall) else 0.0
    return {
        "queries": len(scores),
        "queries_with_loop": positives,
        "true_positives": tp,
        "false_positives": int((accepted & ~correct).sum()),
        "precision": tp / int(accepted.sum()) if accepted.any() else 1.0,
        "recall": tp / positives if positives else 0.0,
        "recall_at_100p": float(recall[perfect].max()) if perfect.any() else 0.0,
        "auc_pr": auc,
        "threshold": threshold,
        "threshold_at_100p": float(thresholds[perfect][-1]) if perfect.any() else float("nan"),
    }


def recall_at_1(correct: np.ndarray, has_loop: np.ndarray) -> float:
    """Share of the queries with a loop whose (best) answer is right; 0.0 when none has a loop."""
    correct, has_loop = np.asarray(correct, dtype=bool), np.asarray(has_loop, dtype=bool)
    positives = int(has_loop.sum())
    return int((correct & has_loop).sum()) / positives if positives else 0.0


def summarise_verified(
    verified: np.ndarray, correct: np.ndarray, inliers: np.ndarray, has_loop: np.ndarray
) -> Mapping[str, float | int]:
    """Figures of the verified answers (module docstring), one entry per query: whether it has a
    verified answer, whether that answer is right, its inlier count, whether the query has a loop."""
    verified = np.asarray(verified, dtype=bool)
    correct = np.asarray(correct, dtype=bool) & verified
    inliers = np.asarray(inliers, dtype=np.float64)
    positives = int(np.asarray(has_loop, dtype=bool).sum())
    tp, accepted = int(correct.sum()), int(verified.sum())
    thresholds, precision, recall = precision_recall_curve(inliers[verified], correct[verified], positives)
    perfect = precision >= 1.0
    return {
        "queries_verified": accepted,
        "true_positives_verified": tp,
        "false_positives_verified": accepted - tp,
        "precision_verified": tp / accepted if accepted else 1.0,
        "recall_verified": tp / positives if positives else 0.0,
        "recall_at_1_verified": recall_at_1(correct, has_loop),
        "recall_at_100p_verified": float(recall[perfect].max()) if perfect.any() else 0.0,
        "inliers_at_100p_verified": float(thresholds[perfect][-1]) if perfect.any() else float("nan"),
    }


#: An accepted loop constraint is wrong when its relative rotation is off the GT's by more than
#: this, or (for cameras at least ``DIRECTION_MIN_BASELINE_M`` apart, where the direction is
#: defined) its translation direction by more than ``WRONG_LOOP_DIRECTION_DEG``. Verified loops on
#: the synthetic scenes are within 1 deg in both (measured); a loop to the wrong place is tens of
#: degrees off in one of them (its direction matches by chance with probability ~7 %).
WRONG_LOOP_ROTATION_DEG = 5.0
WRONG_LOOP_DIRECTION_DEG = 30.0
DIRECTION_MIN_BASELINE_M = 0.2


@dataclass(frozen=True)
class LoopPoseError:
    rotation_deg: float
    direction_deg: float
    baseline_m: float

    @property
    def wrong(self) -> bool:
        if self.rotation_deg > WRONG_LOOP_ROTATION_DEG:
            return True
        return self.baseline_m >= DIRECTION_MIN_BASELINE_M and self.direction_deg > WRONG_LOOP_DIRECTION_DEG


def loop_pose_error(gt_match: np.ndarray, gt_query: np.ndarray, relative: np.ndarray) -> LoopPoseError:
    """How far a loop's relative Sim(3) (the query camera in the match camera's frame, in the map's
    unknown scale) is from the GT relative pose of the two cameras (camera-to-world, metres):
    rotation angle, and angle between the translation directions (the scale is not compared)."""
    truth = np.linalg.inv(gt_match) @ gt_query
    rotation = as_4x4(relative)[:3, :3]
    rotation_deg = float(np.degrees(so3_log_angle(rotation.T @ truth[:3, :3])))
    t_true, t_est = truth[:3, 3], relative[:3, 3]
    norms = float(np.linalg.norm(t_true) * np.linalg.norm(t_est))
    cosine = float(t_true @ t_est) / norms if norms > 0 else 1.0
    direction_deg = float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))
    return LoopPoseError(rotation_deg, direction_deg, float(np.linalg.norm(t_true)))
