"""The registries of the backend's swappable parts, importable without gtsam or pycolmap.

Listing names (``symbio run --help``, ``symbio detectors``) must not load the heavy libraries the
implementations need; the Protocols live next to the implementations (``slam_backend.verify``,
``slam_backend.posegraph``), which re-export these registries.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from frontends.registry import Registry

if TYPE_CHECKING:
    from slam_backend.posegraph import PoseGraphBackend
    from slam_backend.verify import VerifierFactory

VERIFIERS: Registry[VerifierFactory] = Registry(
    "verifier", "symbio.verifiers", {"pycolmap": "slam_backend.verify:create"}
)
BACKENDS: Registry[type[PoseGraphBackend]] = Registry(
    "pose-graph backend", "symbio.backends", {"gtsam": "slam_backend.posegraph:GtsamPoseGraph"}
)
