"""The three pose groups the backend optimises over, behind one small adapter.

``sim3`` (monocular, scale drifts), ``se3`` (metric 3D) and ``se2`` (planar graphs such as city10000)
share one code path in :mod:`slam_backend.posegraph`; only this adapter knows the gtsam classes.

Transforms cross the API as homogeneous numpy matrices: ``sim3`` 4x4 ``[s*R, t; 0, 1]``, ``se3`` 4x4
``[R, t; 0, 1]``, ``se2`` 3x3 ``[R, t; 0, 1]``. Covariances are in gtsam's tangent-space order:

* ``sim3``: 7x7, ``[rotation (3), translation (3), log-scale (1)]`` (``gtsam.Similarity3.Logmap``)
* ``se3``: 6x6, ``[rotation (3), translation (3)]`` (``gtsam.Pose3.Logmap``, rotation first)
* ``se2``: 3x3, ``[x, y, theta]`` (``gtsam.Pose2.Logmap``, translation first)

gtsam's ``Similarity3(R, t, s)`` is the matrix ``[R, t; 0, 1/s]``, i.e. ``[s*R, s*t; 0, 1]``
normalised; the conversions below hide that.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

import gtsam
import numpy as np

Mode = Literal["sim3", "se3", "se2"]
MODES: tuple[Mode, ...] = ("sim3", "se3", "se2")


def similarity_scale(matrix: np.ndarray) -> float:
    """The scale of a 4x4 Sim(3) matrix (its linear part is scale x rotation)."""
    return float(np.cbrt(np.linalg.det(matrix[:3, :3])))


def _sim3_from_matrix(matrix: np.ndarray) -> Any:
    scale = similarity_scale(matrix)
    rotation = gtsam.Rot3(matrix[:3, :3] / scale)
    return gtsam.Similarity3(rotation, matrix[:3, 3] / scale, scale)


def _sim3_to_matrix(value: Any) -> np.ndarray:
    matrix = np.asarray(value.matrix(), dtype=np.float64)
    return matrix / matrix[3, 3]


@dataclass(frozen=True)
class PoseGroup:
    """gtsam classes and conversions for one pose group."""

    mode: Mode
    #: Tangent-space dimension (size of a covariance).
    dim: int
    #: Size of the homogeneous matrix (4 or 3).
    matrix_size: int
    from_matrix: Callable[[np.ndarray], Any]
    to_matrix: Callable[[Any], np.ndarray]
    identity: Callable[[], Any]
    between_factor: Callable[..., Any]
    prior_factor: Callable[..., Any]
    value_at: Callable[[Any, int], Any]
    #: The current iSAM2 estimate of one key.
    isam_value: Callable[[Any, int], Any]
    logmap: Callable[[Any], np.ndarray]
    expmap: Callable[[np.ndarray], Any]
    adjoint: Callable[[Any], np.ndarray]

    def perturb(self, matrix: np.ndarray, covariance: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """``matrix * Exp(e)`` with ``e ~ N(0, covariance)`` (right perturbation, tangent order above)."""
        noise = rng.multivariate_normal(np.zeros(self.dim), covariance)
        return self.to_matrix(self.from_matrix(matrix).compose(self.expmap(noise)))

    def check_matrix(self, matrix: np.ndarray) -> str | None:
        """Why ``matrix`` is not a valid transform of this group, or None when it is."""
        n = self.matrix_size
        if matrix.shape != (n, n):
            return f"expected a {n}x{n} homogeneous matrix, got shape {matrix.shape}"
        if not np.isfinite(matrix).all():
            return "transform contains NaN or inf"
        if not np.allclose(matrix[n - 1], np.eye(n)[n - 1], atol=1e-9):
            return f"last row must be {np.eye(n)[n - 1].tolist()}"
        linear = matrix[: n - 1, : n - 1]
        det = float(np.linalg.det(linear))
        if det <= 0:
            return f"rotation part has non-positive determinant {det:.3g}"
        scale = det ** (1.0 / (n - 1))
        if self.mode != "sim3" and abs(scale - 1.0) > 1e-3:
            return f"{self.mode} transform has scale {scale:.4g}; use mode sim3 for scaled transforms"
        rotation = linear / scale
        if np.abs(rotation @ rotation.T - np.eye(n - 1)).max() > 1e-3:
            return "rotation part is not orthonormal"
        return None


def pose_group(mode: Mode) -> PoseGroup:
    if mode == "sim3":
        return PoseGroup(
            mode="sim3",
            dim=7,
            matrix_size=4,
            from_matrix=_sim3_from_matrix,
            to_matrix=_sim3_to_matrix,
            identity=gtsam.Similarity3,
            between_factor=gtsam.BetweenFactorSimilarity3,
            prior_factor=gtsam.PriorFactorSimilarity3,
            value_at=lambda values, key: values.atSimilarity3(key),
            isam_value=lambda isam, key: isam.calculateEstimateSimilarity3(key),
            logmap=gtsam.Similarity3.Logmap,
            expmap=gtsam.Similarity3.Expmap,
            adjoint=lambda value: value.AdjointMap(),
        )
    if mode == "se3":
        return PoseGroup(
            mode="se3",
            dim=6,
            matrix_size=4,
            from_matrix=lambda matrix: gtsam.Pose3(matrix),
            to_matrix=lambda value: np.asarray(value.matrix(), dtype=np.float64),
            identity=gtsam.Pose3,
            between_factor=gtsam.BetweenFactorPose3,
            prior_factor=gtsam.PriorFactorPose3,
            value_at=lambda values, key: values.atPose3(key),
            isam_value=lambda isam, key: isam.calculateEstimatePose3(key),
            logmap=gtsam.Pose3.Logmap,
            expmap=gtsam.Pose3.Expmap,
            adjoint=lambda value: value.AdjointMap(),
        )
    return PoseGroup(
        mode="se2",
        dim=3,
        matrix_size=3,
        from_matrix=lambda matrix: gtsam.Pose2(gtsam.Rot2.atan2(matrix[1, 0], matrix[0, 0]), matrix[:2, 2]),
        to_matrix=lambda value: np.asarray(value.matrix(), dtype=np.float64),
        identity=gtsam.Pose2,
        between_factor=gtsam.BetweenFactorPose2,
        prior_factor=gtsam.PriorFactorPose2,
        value_at=lambda values, key: values.atPose2(key),
        isam_value=lambda isam, key: isam.calculateEstimatePose2(key),
        logmap=gtsam.Pose2.Logmap,
        expmap=gtsam.Pose2.Expmap,
        adjoint=lambda value: value.AdjointMap(),
    )


def as_4x4(matrix: np.ndarray) -> np.ndarray:
    """A camera pose as a 4x4 SE(3) matrix for evo: scale removed, SE(2) lifted to the plane z=0."""
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape == (3, 3):
        lifted = np.eye(4)
        lifted[:2, :2] = matrix[:2, :2]
        lifted[:2, 3] = matrix[:2, 2]
        return lifted
    pose = matrix.copy()
    pose[:3, :3] /= similarity_scale(pose)
    return pose
