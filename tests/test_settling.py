"""Keyframes settle before their odometry step is read (``LoopClosingConfig.settle_keyframes``).

A stand-in frontend walks a straight line, 1 m per keyframe, with a frame between keyframes. Each
keyframe arrives with its pose off (turned 2 deg, 0.3 m aside, alternately left and right), and its
"bundle adjustment" puts it right when the next two keyframes exist, by moving the same
``Keyframe`` object, as mono-vo's local BA does.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from frontends.base import SettlingFrontend, TrackResult
from frontends.errors import ConfigError
from frontends.mono_vo import MonoVo, MonoVoConfig
from frontends.types import CameraIntrinsics, Keyframe
from lcd.base import LoopCandidate
from slam_backend.pipeline import LoopClosing, LoopClosingConfig
from slam_backend.posegraph import BackendConfig, GtsamPoseGraph

KEYFRAMES = 12
IN_FLUX = 2
COVARIANCE = np.diag([1e-6] * 3 + [1e-4] * 3 + [1e-6])


def gt_pose(position: float) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = position
    return pose


def off(pose: np.ndarray, sign: float) -> np.ndarray:
    wrong = pose.copy()
    wrong[:3, :3] = Rotation.from_euler("z", 2.0 * sign, degrees=True).as_matrix()
    wrong[1, 3] += 0.3 * sign
    return wrong


class Recorder:
    """A loop detector that proposes nothing and records which keyframes it saw, in order."""

    name = "recorder"
    threshold = 1.0

    def __init__(self) -> None:
        self.seen: list[tuple[int, np.ndarray]] = []

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]:
        self.seen.append((keyframe.id, keyframe.pose.copy()))
        return []


def walk(closing: LoopClosing, segment_of=lambda kf_id: 0) -> list[Keyframe]:
    """Keyframe k at frame 2k (pose off until k + IN_FLUX exists), a plain frame at 2k + 1."""
    keyframes: list[Keyframe] = []
    for kf_id in range(KEYFRAMES):
        segment = segment_of(kf_id)
        keyframe = Keyframe(
            kf_id, 2 * kf_id, float(2 * kf_id), off(gt_pose(kf_id), (-1.0) ** kf_id), segment=segment
        )
        keyframe.odometry_covariance = COVARIANCE
        keyframes.append(keyframe)
        if kf_id >= IN_FLUX:
            keyframes[kf_id - IN_FLUX].pose = gt_pose(kf_id - IN_FLUX)  # adjusted now
        closing.add(TrackResult(2 * kf_id, float(2 * kf_id), "tracking", keyframe.pose, segment, keyframe))
        # The frame after the keyframe, tracked against the (not yet adjusted) keyframe.
        frame = keyframe.pose @ gt_pose(0.5)
        closing.add(TrackResult(2 * kf_id + 1, 2 * kf_id + 1.0, "tracking", frame, segment))
    for keyframe in keyframes[-IN_FLUX:]:
        keyframe.pose = gt_pose(keyframe.id)  # the stream ended: the frontend's last poses
    closing.finish()
    return keyframes


def odometry_positions(closing: LoopClosing) -> np.ndarray:
    return np.array([pose[:3, 3] for _, _, pose in closing.frame_poses(corrected=False)])


def test_settled_keyframes_give_the_adjusted_odometry() -> None:
    detector = Recorder()
    closing = LoopClosing(
        GtsamPoseGraph(BackendConfig()), detector, config=LoopClosingConfig(settle_keyframes=IN_FLUX)
    )
    walk(closing)
    positions = odometry_positions(closing)
    np.testing.assert_allclose(positions[::2, 0], np.arange(KEYFRAMES), atol=1e-9)
    np.testing.assert_allclose(positions[::2, 1:], 0.0, atol=1e-9)
    # The frame after the last keyframe keeps its place relative to it: half a metre ahead. The
    # others are blended with their next keyframe (next test), so they lie between the two.
    np.testing.assert_allclose(positions[-1] - positions[-2], [0.5, 0.0, 0.0], atol=1e-9)
    assert np.all((positions[1:-1:2, 0] > positions[0:-2:2, 0]) & (positions[1:-1:2, 0] < positions[2::2, 0]))
    # The loop detector saw every keyframe once, in order, with its adjusted pose.
    assert [kf_id for kf_id, _ in detector.seen] == list(range(KEYFRAMES))
    for kf_id, pose in detector.seen:
        np.testing.assert_allclose(pose, gt_pose(kf_id), atol=1e-12)


def test_steps_read_at_arrival_keep_the_arrival_errors() -> None:
    closing = LoopClosing(GtsamPoseGraph(BackendConfig()), config=LoopClosingConfig(settle_keyframes=0))
    walk(closing)
    sideways = odometry_positions(closing)[::2, 1]
    np.testing.assert_allclose(sideways, 0.3 * (-1.0) ** np.arange(KEYFRAMES), atol=1e-9)


def test_frames_between_keyframes_share_what_the_step_gains_after_they_were_tracked() -> None:
    """Keyframes at x = 0 and 1 with frames at 0.25, 0.5, 0.75 tracked between them; keyframe 1
    then settles at x = 1.2. A frame at time share w follows keyframe 0 by 1 - w and keyframe 1 by
    w, so it moves 0.2 w: no jump of 0.2 m between the last frame and keyframe 1."""
    closing = LoopClosing(GtsamPoseGraph(BackendConfig()), config=LoopClosingConfig(settle_keyframes=1))
    first = Keyframe(0, 0, 0.0, gt_pose(0.0), odometry_covariance=COVARIANCE)
    closing.add(TrackResult(0, 0.0, "tracking", first.pose, 0, first))
    for index in (1, 2, 3):
        closing.add(TrackResult(index, index / 4, "tracking", gt_pose(index / 4), 0))
    second = Keyframe(1, 4, 1.0, gt_pose(1.0), odometry_covariance=COVARIANCE)
    closing.add(TrackResult(4, 1.0, "tracking", second.pose, 0, second))
    second.pose = gt_pose(1.2)  # its bundle adjustment, after the frames were tracked
    closing.finish()
    positions = odometry_positions(closing)
    np.testing.assert_allclose(positions[:, 0], [0.0, 0.3, 0.6, 0.9, 1.2], atol=1e-9)
    np.testing.assert_allclose(positions[:, 1:], 0.0, atol=1e-9)


def test_unsettled_keyframes_must_be_finished_before_reading_poses() -> None:
    closing = LoopClosing(GtsamPoseGraph(BackendConfig()), config=LoopClosingConfig(settle_keyframes=3))
    keyframe = Keyframe(0, 0, 0.0, np.eye(4), odometry_covariance=COVARIANCE)
    closing.add(TrackResult(0, 0.0, "tracking", np.eye(4), 0, keyframe))
    assert closing.keyframes == []
    with pytest.raises(RuntimeError, match="finish"):
        closing.frame_poses(corrected=False)
    closing.finish()
    assert [kf.id for kf in closing.keyframes] == [0]
    assert len(closing.frame_poses(corrected=False)) == 1


def test_a_new_segment_settles_the_old_one() -> None:
    detector = Recorder()
    closing = LoopClosing(
        GtsamPoseGraph(BackendConfig()), detector, config=LoopClosingConfig(settle_keyframes=5)
    )
    keyframes = []
    for kf_id in range(4):
        keyframe = Keyframe(kf_id, kf_id, float(kf_id), gt_pose(kf_id), segment=kf_id // 3)
        keyframes.append(keyframe)
        closing.add(TrackResult(kf_id, float(kf_id), "tracking", keyframe.pose, kf_id // 3, keyframe))
    # Keyframe 3 opened segment 1: segment 0's keyframes went on; keyframe 3 waits.
    assert [kf_id for kf_id, _ in detector.seen] == [0, 1, 2]
    closing.finish()
    assert [kf_id for kf_id, _ in detector.seen] == [0, 1, 2, 3]


def test_mono_vo_settles_after_its_bundle_adjustment_window() -> None:
    camera = CameraIntrinsics(500.0, 500.0, 320.0, 240.0, 640, 480)
    frontend = MonoVo(camera, MonoVoConfig())
    assert isinstance(frontend, SettlingFrontend)
    assert frontend.keyframes_in_flux == MonoVoConfig().ba.window


def test_a_negative_settle_count_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="settle_keyframes must be >= 0"):
        LoopClosingConfig(settle_keyframes=-1)
