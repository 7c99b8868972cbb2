"""The full SLAM system (``Slam``) and its GTSAM pose-graph backend: Sim(3)/SE(3)/SE(2) graphs on
iSAM2 with PCM / GNC loop outlier rejection.

``slam`` (``Slam``, ``SlamResult``: the system you import), ``pipeline`` (``LoopClosing``: detector,
verifier and backend per keyframe), ``verify`` (geometric verification), ``posegraph`` (Protocol +
``GtsamPoseGraph``), ``plugins`` (``VERIFIERS`` / ``BACKENDS`` registries), ``pcm`` (pairwise
consistency), ``lie`` (group adapters, matrix and covariance layouts), ``graph_io`` (g2o / TORO /
city10000 in, g2o out), ``simulate`` (monocular drift problems from GT trajectories), ``experiment``
(run + evo ATE), ``plot``, ``cli`` (``symbio posegraph``).

``from slam_backend import Slam`` imports the system on first use only, so that importing a light
module of the package (the registries) does not load gtsam and pycolmap.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from slam_backend.slam import Slam, SlamResult, SlamState

__all__ = ["Slam", "SlamResult", "SlamState"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from slam_backend import slam

        return getattr(slam, name)
    raise AttributeError(f"module 'slam_backend' has no attribute {name!r}")
