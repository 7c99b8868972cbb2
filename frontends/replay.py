"""``replay``: a frontend whose poses come from a trajectory file instead of visual odometry.

It lets the loop detector and the backend be evaluated on someone else's odometry (an ORB-SLAM
``CameraTrajectory.txt``, a VIO log, or the ground truth itself). Each frame gets the file's pose
and state "tracking"; a frame the file has no pose for is "lost". Gaps are reported that way and
never interpolated: an ORB-SLAM ``KeyFrameTrajectory.txt`` therefore tracks only its keyframes.

Matching frames to poses:

* ``format: tum`` (``timestamp tx ty tz qx qy qz qw``): the pose with the nearest timestamp within
  ``max_time_difference`` seconds (TUM's ``associate.py`` tolerance, 0.02 s, by default).
* ``format: kitti`` (12 numbers per line, no time): line k is frame k of the dataset.

Keyframes: a tracked frame becomes a keyframe when ``keyframe_period`` seconds have passed since
the previous keyframe or, when ``keyframe_distance`` and/or ``keyframe_angle_deg`` are set, when
the camera moved or turned that much since then (the period is then unused; distances are in the
file's units). A due frame with fewer than ``min_features`` ORB features is passed over and the
next one tried. Keyframes carry ORB keypoints and descriptors, the image and the file's pose, in
segment 0; there are no map points and no odometry covariance.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from frontends.base import TrackResult
from frontends.config import load_config
from frontends.datasets.base import associate_nearest
from frontends.errors import ConfigError
from frontends.orb import OrbConfig, extract_orb
from frontends.trajectory_io import read_kitti_poses, read_tum
from frontends.types import CameraIntrinsics, Frame, Keyframe

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReplayConfig:
    #: The trajectory file (camera-to-world poses); relative paths are relative to the working folder.
    trajectory: str = ""
    #: Trajectory file format: tum (timestamped) or kitti (one pose per frame).
    format: Literal["tum", "kitti"] = "tum"
    #: TUM files: the largest |frame time - pose time| (s) that still matches.
    max_time_difference: float = 0.02
    #: Seconds between keyframes, unless a motion threshold below is set.
    keyframe_period: float = 0.2
    #: Camera-centre distance (file units) since the last keyframe that makes a keyframe.
    keyframe_distance: float | None = None
    #: Rotation (deg) since the last keyframe that makes a keyframe.
    keyframe_angle_deg: float | None = None
    #: A frame with fewer ORB features does not become a keyframe (the loop detectors' own floor).
    min_features: int = 20
    #: ORB extraction of the keyframes (place-recognition preset).
    orb: OrbConfig = field(default_factory=OrbConfig)

    def __post_init__(self) -> None:
        if self.max_time_difference < 0 or self.keyframe_period < 0 or self.min_features < 0:
            raise ConfigError("replay: max_time_difference, keyframe_period and min_features must be >= 0")
        for name in ("keyframe_distance", "keyframe_angle_deg"):
            value = getattr(self, name)
            if value is not None and value <= 0:
                raise ConfigError(f"replay: {name} must be positive (or null to use keyframe_period)")

    @property
    def keyframes_by_motion(self) -> bool:
        return self.keyframe_distance is not None or self.keyframe_angle_deg is not None


class Replay:
    """Replays the poses of a trajectory file; see the module docstring."""

    name = "replay"

    def __init__(self, config: ReplayConfig) -> None:
        if not config.trajectory:
            raise ConfigError("replay: no trajectory file; pass --set trajectory=FILE (and format=kitti)")
        self.config = config
        self.path = Path(config.trajectory)
        trajectory = read_tum(self.path) if config.format == "tum" else read_kitti_poses(self.path)
        self.poses = np.asarray(trajectory.poses_se3, dtype=np.float64)
        self.pose_timestamps = np.asarray(trajectory.timestamps, dtype=np.float64)
        self._keyframes: list[Keyframe] = []
        self._in_gap = False
        self._gaps = 0

    def pose_index(self, frame: Frame) -> int:
        """Row of the file that holds ``frame``'s pose, or -1."""
        if self.config.format == "kitti":
            return frame.index if frame.index < len(self.poses) else -1
        stamp = np.array([frame.timestamp])
        return int(associate_nearest(stamp, self.pose_timestamps, self.config.max_time_difference)[0])

    def track(self, frame: Frame) -> TrackResult:
        row = self.pose_index(frame)
        if row < 0:
            self._report_gap(frame)
            return TrackResult(frame.index, frame.timestamp, "lost", None)
        self._in_gap = False
        pose = self.poses[row].copy()
        keyframe = self._make_keyframe(frame, pose) if self._keyframe_due(frame, pose) else None
        return TrackResult(frame.index, frame.timestamp, "tracking", pose, 0, keyframe)

    def keyframes(self) -> list[Keyframe]:
        return list(self._keyframes)

    def _report_gap(self, frame: Frame) -> None:
        if self._in_gap:
            return
        self._in_gap = True
        self._gaps += 1
        # The first gap is a warning (often a wrong format or time base); later ones are counted as lost.
        level = logging.WARNING if self._gaps == 1 else logging.DEBUG
        log.log(
            level,
            "%s has no pose for frame %d (t=%.6f s, %s); such frames are reported lost, not interpolated",
            self.path,
            frame.index,
            frame.timestamp,
            frame.path or "no image path",
        )

    def _keyframe_due(self, frame: Frame, pose: np.ndarray) -> bool:
        if not self._keyframes:
            return True
        last = self._keyframes[-1]
        if not self.config.keyframes_by_motion:
            return frame.timestamp - last.timestamp >= self.config.keyframe_period - 1e-9
        moved = float(np.linalg.norm(pose[:3, 3] - last.pose[:3, 3]))
        relative = last.pose[:3, :3].T @ pose[:3, :3]
        turned = math.degrees(math.acos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0)))
        distance, angle = self.config.keyframe_distance, self.config.keyframe_angle_deg
        return (distance is not None and moved >= distance) or (angle is not None and turned >= angle)

    def _make_keyframe(self, frame: Frame, pose: np.ndarray) -> Keyframe | None:
        keypoints, descriptors = extract_orb(frame.gray, self.config.orb)
        if len(keypoints) < self.config.min_features:
            return None
        keyframe = Keyframe(
            id=len(self._keyframes),
            frame_index=frame.index,
            timestamp=frame.timestamp,
            pose=pose,
            keypoints=keypoints,
            descriptors=descriptors,
            image=frame.image,
            points3d=None,
            segment=0,
            odometry_covariance=None,
        )
        self._keyframes.append(keyframe)
        return keyframe


def create(
    camera: CameraIntrinsics, overrides: Sequence[str] = (), config_path: str | Path | None = None
) -> Replay:
    """The replay frontend configured by a YAML file and ``key=value`` overrides.

    ``camera`` is part of the frontend factory signature; replayed poses do not need it.
    """
    try:
        config = load_config(ReplayConfig, config_path, overrides)
    except ValueError as exc:  # OrbConfig validates itself with ValueError
        raise ConfigError(f"replay: {exc}") from None
    return Replay(config)
