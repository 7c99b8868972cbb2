"""The odometry across a map restart: the new segment continues at the old one's velocity and scale.

The camera walks along x at 1 m/s, a keyframe per second. Tracking is lost for 3 s after the tenth
keyframe; the new segment's map has its own frame (turned and shifted) and its own unit (a
monocular restart: here 4 map units per metre). No loop joins the two.
"""

from __future__ import annotations

import numpy as np
import pytest

from frontends.base import TrackResult
from frontends.errors import ConfigError
from frontends.types import Keyframe
from slam_backend.pipeline import LoopClosing, LoopClosingConfig
from slam_backend.posegraph import BackendConfig, GtsamPoseGraph

COVARIANCE = np.diag([1e-6] * 3 + [1e-4] * 3 + [1e-6])
FIRST_SEGMENT = range(10)
GAP_S = 3.0
NEW_MAP_UNITS_PER_METRE = 4.0
#: Where the new segment's map frame lies (camera-to-world of its origin in the first map's frame).
NEW_MAP_FRAME = np.array([[0.0, -1.0, 0.0, 5.0], [1.0, 0.0, 0.0, -3.0], [0.0, 0.0, 1.0, 2.0], [0, 0, 0, 1]])


def timestamp(kf_id: int) -> float:
    return float(kf_id) + (GAP_S if kf_id >= len(FIRST_SEGMENT) else 0.0)


def true_pose(kf_id: int) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = timestamp(kf_id)  # 1 m/s along x, the camera's own x axis
    return pose


def in_new_map(pose: np.ndarray, units_per_metre: float) -> np.ndarray:
    """The pose as the new segment's frontend reports it: relative to its first keyframe, in its units."""
    first = true_pose(len(FIRST_SEGMENT))
    local = np.linalg.inv(first) @ pose
    local[:3, 3] *= units_per_metre
    return NEW_MAP_FRAME @ local


def run(
    new_keyframes: int, config: LoopClosingConfig, units_per_metre: float = NEW_MAP_UNITS_PER_METRE
) -> dict[int, np.ndarray]:
    closing = LoopClosing(GtsamPoseGraph(BackendConfig()), config=config)
    for kf_id in range(len(FIRST_SEGMENT) + new_keyframes):
        segment = int(kf_id >= len(FIRST_SEGMENT))
        pose = true_pose(kf_id) if segment == 0 else in_new_map(true_pose(kf_id), units_per_metre)
        keyframe = Keyframe(
            kf_id, kf_id, timestamp(kf_id), pose, segment=segment, odometry_covariance=COVARIANCE
        )
        closing.add(TrackResult(kf_id, timestamp(kf_id), "tracking", pose, segment, keyframe))
    closing.finish()
    return {index: pose for index, _, pose in closing.frame_poses(corrected=False)}


def test_a_new_segment_continues_at_the_old_velocity_and_scale() -> None:
    poses = run(8, LoopClosingConfig())
    for kf_id, pose in poses.items():
        np.testing.assert_allclose(pose[:3, 3], true_pose(kf_id)[:3, 3], atol=1e-6)
        np.testing.assert_allclose(pose[:3, :3], np.eye(3), atol=1e-6)  # a camera pose, not a Sim(3)


def test_without_a_speed_window_the_new_segment_starts_on_the_last_keyframe_in_its_own_units() -> None:
    poses = run(8, LoopClosingConfig(segment_link_speed_window_s=0.0))
    last_old, first_new, second_new = len(FIRST_SEGMENT) - 1, len(FIRST_SEGMENT), len(FIRST_SEGMENT) + 1
    np.testing.assert_allclose(poses[first_new][:3, 3], poses[last_old][:3, 3], atol=1e-6)
    step = np.linalg.norm(poses[second_new][:3, 3] - poses[first_new][:3, 3])
    assert step == pytest.approx(NEW_MAP_UNITS_PER_METRE)


def test_a_scale_change_beyond_the_limit_means_a_runaway_map_and_the_link_is_identity() -> None:
    """20 new units per old one: more than two initialisations of one scene differ by (default 5x)."""
    poses = run(8, LoopClosingConfig(), units_per_metre=20.0)
    last_old, first_new, second_new = len(FIRST_SEGMENT) - 1, len(FIRST_SEGMENT), len(FIRST_SEGMENT) + 1
    np.testing.assert_allclose(poses[first_new][:3, 3], poses[last_old][:3, 3], atol=1e-6)
    assert np.linalg.norm(poses[second_new][:3, 3] - poses[first_new][:3, 3]) == pytest.approx(20.0)
    linked = run(8, LoopClosingConfig(segment_link_max_scale_change=25.0), units_per_metre=20.0)
    np.testing.assert_allclose(linked[second_new][:3, 3], true_pose(second_new)[:3, 3], atol=1e-6)


def test_a_new_segment_of_one_keyframe_has_no_speed_and_is_linked_by_identity() -> None:
    poses = run(1, LoopClosingConfig())
    np.testing.assert_allclose(
        poses[len(FIRST_SEGMENT)][:3, 3], poses[len(FIRST_SEGMENT) - 1][:3, 3], atol=1e-6
    )


def test_bad_link_settings_are_config_errors() -> None:
    with pytest.raises(ConfigError, match="segment_link_speed_window_s"):
        LoopClosingConfig(segment_link_speed_window_s=-1.0)
    with pytest.raises(ConfigError, match="segment_link_max_scale_change"):
        LoopClosingConfig(segment_link_max_scale_change=1.0)
