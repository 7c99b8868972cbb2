"""``mono-vo``: monocular visual odometry with a local map, GTSAM local bundle adjustment,
relocalisation and map segments (ORB-SLAM's tracking design on OpenCV, scipy and GTSAM).

Modules: ``config`` (settings), ``features`` (ORB on a grid, vectorised matching), ``initializer``
(two-view H/E model selection), ``tracker`` (local-map tracking, relocalisation), ``map`` (points
and keyframes of a segment), ``local_ba`` (GTSAM bundle adjustment), ``masking`` (which detected
movable objects to keep out of the map), ``frontend`` (the state machine). Registered in
``frontends.base.FRONTENDS`` as ``mono-vo``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from frontends.config import load_config
from frontends.mono_vo.config import MonoVoConfig
from frontends.mono_vo.frontend import MonoVo
from frontends.types import CameraIntrinsics


def create(
    camera: CameraIntrinsics, overrides: Sequence[str] = (), config_path: str | Path | None = None
) -> MonoVo:
    """The frontend for ``camera``, configured by a YAML file and ``key=value`` overrides."""
    return MonoVo(camera, load_config(MonoVoConfig, config_path, overrides))


__all__ = ["MonoVo", "MonoVoConfig", "create"]
