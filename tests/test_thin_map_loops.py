"""Loops where the map is thin: deferred and verified again, or joining two map segments by their
two-view geometry (``LoopClosing``, "Deferred loops"; ``slam_backend.two_view_join``).

A generated scene: 1 500 points in a box, each with its own ORB-like descriptor; the camera walks
out along x (keyframes 0-7, 1.2 m apart) and back 0.3 m to the side (8-15), so keyframe 12 sees
keyframe 2's place (and 13 nearly so). Keyframes carry the projections of the points they see
(0.3 px noise), their descriptors and the points in their own camera frame; "thin" keyframes have
map points on only 5 % of the points that keyframe 2 sees (elsewhere on all), so the real
verifier's two-view stage passes and too few of its inliers have a map point in both keyframes.
Split in two map segments (``split``), the way back (8-15) is a second map in its own frame and
units, and the two maps hold disjoint points (the first the even ones, the second the odd ones).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from frontends.base import TrackResult
from frontends.errors import ConfigError
from frontends.types import CameraIntrinsics, Keyframe
from lcd.base import LoopCandidate
from slam_backend.pipeline import LoopClosing, LoopClosingConfig, LoopRecord
from slam_backend.posegraph import BackendConfig, GtsamPoseGraph
from slam_backend.two_view_join import TwoViewJoinConfig
from slam_backend.verify import PycolmapVerifier, Verification, Verifier

CAMERA = CameraIntrinsics(800.0, 800.0, 320.0, 240.0, 640, 480)
K = np.array([[800.0, 0, 320.0], [0, 800.0, 240.0], [0, 0, 1]])
KEYFRAMES = 16
COVARIANCE = np.diag([1e-6] * 3 + [1e-4] * 3 + [1e-6])
_rng = np.random.default_rng(7)
POINTS = np.column_stack([_rng.uniform(-4, 13, 1500), _rng.uniform(-2, 2, 1500), _rng.uniform(4, 8, 1500)])
DESCRIPTORS = _rng.integers(0, 256, (1500, 32), dtype=np.uint8)
#: The few points a thin keyframe holds among those keyframe 2 sees (the same few in every one).
SPARSE = _rng.random(1500) < 0.05


def gt_pose(kf_id: int) -> np.ndarray:
    """Camera-to-world: out along x, then back 0.3 m further and 0.15 m to the side."""
    pose = np.eye(4)
    x = 1.2 * kf_id if kf_id < 8 else 1.2 * (14 - kf_id) + 0.3
    pose[:3, 3] = (x, 0.0 if kf_id < 8 else 0.15, 0.0)
    return pose


def visible(kf_id: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices of the points the keyframe sees, their pixels and their camera-frame positions."""
    pose = gt_pose(kf_id)
    camera = (POINTS - pose[:3, 3]) @ pose[:3, :3]
    pixels = camera @ K.T
    pixels = pixels[:, :2] / pixels[:, 2:]
    inside = (camera[:, 2] > 0) & (pixels >= 0).all(axis=1) & (pixels < (640, 480)).all(axis=1)
    return np.flatnonzero(inside), pixels[inside], camera[inside]


SEEN_BY_2 = set(visible(2)[0].tolist())
#: The second segment's map: X_map = UNITS (ROTATION X_world + OFFSET).
UNITS = 2.0
ROTATION = np.array([[np.cos(0.5), -np.sin(0.5), 0.0], [np.sin(0.5), np.cos(0.5), 0.0], [0.0, 0.0, 1.0]])
OFFSET = np.array([1.0, -2.0, 0.5])


def keyframe(kf_id: int, thin: bool = False, split: bool = False) -> Keyframe:
    """The keyframe; ``thin``: map points on only the ``SPARSE`` few of what keyframe 2 sees;
    ``split``: keyframes 8-15 are a second segment (see the module docstring)."""
    ids, pixels, camera = visible(kf_id)
    noise = np.random.default_rng(kf_id).normal(0.0, 0.3, pixels.shape)
    mapped = np.array([not (thin and i in SEEN_BY_2) or SPARSE[i] for i in ids])
    segment, pose = 0, gt_pose(kf_id)
    if split:
        segment = int(kf_id >= 8)
        mapped &= ids % 2 == segment
    if segment:
        pose[:3, :3] = ROTATION @ pose[:3, :3]
        pose[:3, 3] = UNITS * (ROTATION @ pose[:3, 3] + OFFSET)
        camera = UNITS * camera
    points3d = np.where(mapped[:, None], camera, np.nan)
    return Keyframe(
        kf_id, kf_id, float(kf_id), pose, (pixels + noise).astype(np.float32), DESCRIPTORS[ids],
        points3d=points3d, point_ids=np.where(mapped, ids, -1), segment=segment,
        odometry_covariance=COVARIANCE,
    )  # fmt: skip


def filled(kf: Keyframe) -> None:
    """What a frontend does when it refreshes a keyframe that gained map points."""
    full = keyframe(kf.id)
    kf.points3d, kf.point_ids = full.points3d, full.point_ids


class ChosenCandidates:
    name = "chosen"
    threshold = 0.5

    def __init__(self, proposals: dict[int, int]) -> None:
        self.proposals = proposals  # query keyframe -> match keyframe

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]:
        match = self.proposals.get(keyframe.id)
        return [] if match is None else [LoopCandidate(keyframe.id, match, 1.0, {})]


class FirstCallThin:
    """The real verifier, except that its first answer is a two-view pass on a thin map (as
    repeated texture can make two views of different places agree)."""

    name = "first-call-thin"

    def __init__(self) -> None:
        self.real = PycolmapVerifier(CAMERA)
        self.calls = 0

    def verify(self, query: Keyframe, match: Keyframe) -> Verification:
        self.calls += 1
        if self.calls == 1:
            reason = "8 inliers with map points < 30"
            return Verification(query.id, match.id, False, reason, 120, 90, thin_map=True)
        return self.real.verify(query, match)


def run(
    proposals: dict[int, int],
    thin: set[int],
    *,
    verifier: Verifier | None = None,
    on_add: dict[int, Callable[[dict[int, Keyframe]], None]] | None = None,
    keyframes: int = KEYFRAMES,
    split: bool = False,
    **config: Any,
) -> tuple[LoopClosing, dict[int, Keyframe]]:
    """Every keyframe through loop closing (no settling delay); ``on_add[k](made)`` runs before
    keyframe k goes in (a frontend refreshing earlier keyframes)."""
    closing = LoopClosing(
        GtsamPoseGraph(BackendConfig()),
        ChosenCandidates(proposals),
        None,
        verifier or PycolmapVerifier(CAMERA),
        LoopClosingConfig(**config),
        camera=CAMERA,
    )
    made: dict[int, Keyframe] = {}
    for kf_id in range(keyframes):
        if on_add and kf_id in on_add:
            on_add[kf_id](made)
        made[kf_id] = kf = keyframe(kf_id, thin=kf_id in thin, split=split)
        closing.add(TrackResult(kf_id, float(kf_id), "tracking", kf.pose, kf.segment, kf))
    closing.finish()
    return closing, made


def only(closing: LoopClosing) -> LoopRecord:
    (record,) = closing.loops()
    return record


def test_a_thin_map_rejects_a_true_loop_without_deferral() -> None:
    record = only(run({12: 2}, thin={12}, defer_retries=0)[0])
    assert not record.accepted and record.deferrals == 0
    assert record.reason.endswith("inliers with map points < 30")


def test_deferred_loop_is_accepted_once_the_query_gained_map_points() -> None:
    closing, _ = run({12: 2}, thin={12, 13}, on_add={14: lambda made: filled(made[12])})
    record = only(closing)
    assert record.accepted and record.verified
    assert (record.query, record.match) == (12, 2)
    assert record.deferrals == 2  # the first verification and retry 1 (13 -> 2)
    assert record.reason.startswith("accepted after deferral (12 -> 2: ")
    assert "verified as 12 -> 2 at retry 2" in record.reason
    truth = np.linalg.inv(gt_pose(2)) @ gt_pose(12)
    assert record.relative is not None
    np.testing.assert_allclose(record.relative, truth, atol=0.02)


def test_deferred_loop_is_accepted_from_a_later_view_of_the_place() -> None:
    closing, _ = run({12: 2}, thin={12})
    record = only(closing)
    assert record.accepted
    # The row shows the pair that was verified: keyframe 13, the next settled one.
    assert (record.query, record.match, record.deferrals) == (13, 2, 1)
    assert record.reason.startswith("accepted after deferral")
    truth = np.linalg.inv(gt_pose(2)) @ gt_pose(13)
    assert record.relative is not None
    np.testing.assert_allclose(record.relative, truth, atol=0.02)
    estimates = closing.corrected_keyframe_poses()
    assert np.linalg.norm(estimates[13][:3, 3] - gt_pose(13)[:3, 3]) < 0.05


def test_deferral_gives_up_when_the_retries_run_out() -> None:
    # Retry 1 (13 -> 2) finds the map still thin; 14 and 15 share too few map points with 12.
    closing, _ = run({12: 2}, thin={12, 13, 14, 15})
    record = only(closing)
    assert not record.accepted and not record.verified and record.deferrals == 2
    assert record.reason.startswith("gave up after 3 retries: the query's segment left the place; ")
    assert record.reason.endswith("retry 3 skipped: keyframe 15 shares 6 map points with 12")
    assert closing.backend.decisions() == {}
    record = only(run({12: 2}, thin={12, 13}, defer_retries=1)[0])
    assert record.reason.startswith("gave up after 1 retry: the map stayed too thin there; deferred: ")
    assert record.reason.endswith("retry 1 (13 -> 2): 12 inliers with map points < 30")


def test_deferral_gives_up_when_the_stream_ends() -> None:
    closing, _ = run({12: 2}, thin={12}, keyframes=13)
    record = only(closing)
    assert record.reason.startswith("gave up after 0 retries: the stream ended; deferred: ")


def test_a_deferred_candidate_proposed_again_is_superseded() -> None:
    closing, _ = run({12: 2, 13: 2}, thin={12})
    first, second = closing.loops()
    assert first.query == 12 and first.reason.startswith("superseded by candidate 13 -> 2; deferred: ")
    assert not first.accepted and first.deferrals == 1
    assert second.query == 13 and second.accepted and second.deferrals == 0


def test_a_false_candidate_is_not_accepted_through_deferral() -> None:
    # Keyframe 7 is 5 m from keyframe 12's place; the first answer (a two-view pass on a thin map)
    # is wrong, and the retry meets the real verifier.
    verifier = FirstCallThin()
    closing, _ = run({12: 7}, thin=set(), verifier=verifier)
    record = only(closing)
    assert not record.accepted and not record.verified
    assert record.reason.startswith("rejected after deferral: ")
    assert "(retry 1 (13 -> 7); deferred: 8 inliers with map points < 30)" in record.reason
    assert verifier.calls == 2
    assert closing.backend.decisions() == {}


def test_a_candidate_whose_images_disagree_is_not_deferred() -> None:
    record = only(run({12: 7}, thin={12})[0])
    assert record.deferrals == 0 and "descriptor matches" in record.reason


def test_two_thin_loops_join_two_map_segments_by_their_two_view_geometry() -> None:
    # Two looks at the place: other keyframes on both sides (``bridge_min_interval_s``).
    closing, _ = run({12: 2, 13: 3}, thin=set(), split=True)
    records = closing.loops()
    assert [(r.query, r.accepted, r.two_view, r.deferrals) for r in records] == [
        (12, True, True, 0),
        (13, True, True, 0),
    ]
    assert all(r.reason.startswith("accepted by two-view join (") for r in records)
    for r in records:  # the query's map units are 1 / UNITS of the match's
        truth = np.linalg.inv(gt_pose(r.match)) @ gt_pose(r.query)
        assert r.relative is not None
        assert r.scale == pytest.approx(1.0 / UNITS, rel=0.03)
        rotation = r.relative[:3, :3] / r.scale @ truth[:3, :3].T  # camera to camera: no map frame
        assert np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1, 1))) < 0.5
        np.testing.assert_allclose(r.relative[:3, 3], truth[:3, 3], atol=0.05)
    # The second segment now lies where it is: every keyframe within 10 cm of the truth.
    estimates = closing.corrected_keyframe_poses()
    errors = [np.linalg.norm(estimates[k][:3, 3] - gt_pose(k)[:3, 3]) for k in range(KEYFRAMES)]
    assert max(errors) < 0.1


def test_a_lone_two_view_join_waits_for_support() -> None:
    record = only(run({12: 2}, thin=set(), split=True)[0])
    assert not record.accepted and record.verified and record.two_view
    assert record.reason.startswith("held: joins map segments 0 and 1; waits for 1 more")
    assert "; by two-view join (" in record.reason


class TurnedTwoView:
    """The real verifier, except that the two-view pose of ``query``'s candidates is turned 20 deg
    about the vertical (as a wrong place whose views happen to agree would give)."""

    name = "turned-two-view"

    def __init__(self, query: int) -> None:
        self.real = PycolmapVerifier(CAMERA)
        self.query = query

    def verify(self, query: Keyframe, match: Keyframe) -> Verification:
        found = self.real.verify(query, match)
        two_view = found.two_view
        if query.id != self.query or two_view is None or two_view.match_from_query is None:
            return found
        turn = np.radians(20.0)
        about_y = np.array([[np.cos(turn), 0, np.sin(turn)], [0, 1, 0], [-np.sin(turn), 0, np.cos(turn)]])
        pose = about_y @ two_view.match_from_query
        return replace(found, two_view=replace(two_view, match_from_query=pose))


def test_a_wrong_two_view_join_does_not_support_a_right_one() -> None:
    closing, _ = run({12: 2, 13: 3}, thin=set(), split=True, verifier=TurnedTwoView(13))
    records = closing.loops()
    assert [(r.query, r.accepted, r.two_view) for r in records] == [(12, False, True), (13, False, True)]
    assert all(r.reason.startswith("held: joins map segments 0 and 1") for r in records)
    assert closing.backend.decisions() == {}


def test_without_the_join_a_thin_loop_between_segments_is_deferred() -> None:
    record = only(run({12: 2}, thin=set(), split=True, two_view_join=TwoViewJoinConfig(enabled=False))[0])
    assert not record.accepted and not record.two_view and record.deferrals > 0


def test_deferral_config_is_validated() -> None:
    with pytest.raises(ConfigError):
        LoopClosingConfig(defer_retries=-1)
    with pytest.raises(ConfigError):
        LoopClosingConfig(defer_min_shared_points=0)
    with pytest.raises(ConfigError):
        TwoViewJoinConfig(min_consistent_ratio=0.0)
    with pytest.raises(ConfigError):
        TwoViewJoinConfig(rotation_sigma=0.0)
