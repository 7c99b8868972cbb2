"""Which candidates a SLAM run checks geometrically: the detector's ``proposal_threshold`` when it
has one (symbiolcd2: any positive score), else ``loop_closing.proposal_ratio`` x its threshold."""

from __future__ import annotations

import numpy as np
import pytest

from frontends.base import TrackResult
from frontends.types import Keyframe
from lcd.base import LoopCandidate
from lcd.symbiolcd2 import create as create_symbiolcd2
from slam_backend.pipeline import LoopClosing, LoopClosingConfig
from slam_backend.posegraph import BackendConfig, GtsamPoseGraph
from slam_backend.verify import Verification

#: Scores the detector gives keyframe 20's candidates, best first.
SCORES = {5: 0.3, 6: 0.004, 7: -0.01}


class Scored:
    name = "scored"
    threshold = 0.5

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]:
        if keyframe.id != 20:
            return []
        return [LoopCandidate(20, match, score, {}) for match, score in SCORES.items()]


class WithFloor(Scored):
    proposal_threshold = 0.0


class Counting:
    """Rejects everything; remembers which pairs it was asked to check."""

    name = "counting"

    def __init__(self) -> None:
        self.checked: list[int] = []

    def verify(self, query: Keyframe, match: Keyframe) -> Verification:
        self.checked.append(match.id)
        return Verification(query.id, match.id, False, "test: rejected", 0, 0)


def checked(detector: Scored, **config: float) -> list[int]:
    verifier = Counting()
    closing = LoopClosing(
        GtsamPoseGraph(BackendConfig()),
        detector,  # type: ignore[arg-type]
        None,
        verifier,  # type: ignore[arg-type]
        LoopClosingConfig(max_verifications=3, **config),  # type: ignore[arg-type]
    )
    rng = np.random.default_rng(0)
    for kf_id in range(21):
        pose = np.eye(4)
        pose[0, 3] = 0.1 * kf_id
        keyframe = Keyframe(
            kf_id,
            kf_id,
            float(kf_id),
            pose,
            rng.uniform(0, 320, (50, 2)).astype(np.float32),
            rng.integers(0, 256, (50, 32), dtype=np.uint8),
        )
        closing.add(TrackResult(kf_id, float(kf_id), "tracking", pose, 0, keyframe))
    return verifier.checked


def test_without_a_proposal_threshold_the_ratio_of_the_threshold_gates() -> None:
    assert checked(Scored()) == [5]  # 0.5 x 0.5: only 0.3 passes
    assert checked(Scored(), proposal_ratio=0.001) == [5, 6]
    assert checked(Scored(), proposal_ratio=0.0) == [5, 6]  # never a score <= 0


def test_the_detectors_proposal_threshold_wins() -> None:
    assert checked(WithFloor()) == [5, 6]
    assert checked(WithFloor(), proposal_ratio=0.9) == [5, 6]


def test_symbiolcd2_verifies_every_positive_score_by_default() -> None:
    detector = create_symbiolcd2()
    assert detector.proposal_threshold == 0.0 and detector.threshold == pytest.approx(0.011)
    assert create_symbiolcd2(["proposal_threshold=0.02"]).proposal_threshold == 0.02
