"""Small geometric helpers: pose conversions, projection, triangulation, seeded USAC parameters.

Poses inside the frontend are world-to-camera (``T_cw``, what projection needs); the API gives
camera-to-world. Image points are undistorted pixels, so the pinhole matrix K is the whole camera.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import cv2
import numpy as np


def usac_params(
    seed: int, threshold: float, *, thorough: bool = True, max_iterations: int = 1000
) -> cv2.UsacParams:
    """OpenCV USAC with its own random state (no global RNG).

    ``thorough``: MAGSAC++ scoring with local optimisation, for the rare, decisive two-view fits of
    initialisation. Otherwise MSAC without local optimisation (5-7x faster), for per-frame PnP
    whose inlier share is high and whose pose is refined afterwards anyway.
    """
    params = cv2.UsacParams()
    params.randomGeneratorState = int(seed) % (2**31 - 1)
    params.threshold = float(threshold)
    params.confidence = 0.999
    params.maxIterations = max_iterations
    params.sampler = cv2.SAMPLING_UNIFORM
    params.isParallel = False
    params.final_polisher = cv2.MAGSAC if thorough else cv2.LSQ_POLISHER
    params.final_polisher_iterations = 10 if thorough else 3
    if thorough:
        params.score = cv2.SCORE_METHOD_MAGSAC
        params.loMethod = cv2.LOCAL_OPTIM_SIGMA
        params.loIterations = 10
        params.loSampleSize = 14
    else:
        params.score = cv2.SCORE_METHOD_MSAC
        params.loMethod = cv2.LOCAL_OPTIM_NULL
    return params


def fit_or_none(estimator: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """Run an OpenCV RANSAC estimator; None when it rejects degenerate data with ``cv2.error``
    (USAC asserts on an empty model instead of returning one)."""
    try:
        return estimator(*args, **kwargs)
    except cv2.error:
        return None


def frame_seed(seed: int, frame_index: int, stage: int = 0) -> int:
    """A RANSAC seed that differs per frame and stage yet is fixed by the config seed."""
    return (seed * 1_000_003 + frame_index * 17 + stage) % (2**31 - 1)


def invert(T: np.ndarray) -> np.ndarray:
    inverse = np.eye(4)
    rotation = T[:3, :3]
    inverse[:3, :3] = rotation.T
    inverse[:3, 3] = -rotation.T @ T[:3, 3]
    return inverse


def from_rvec(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3))[0]
    T[:3, 3] = np.asarray(tvec, np.float64).reshape(3)
    return T


def transform(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return linear_map(T[:3, :3], points) + T[:3, 3]


def linear_map(M: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """``vectors @ M.T`` for (N, 3) vectors, elementwise: a BLAS call for a 3x3 matrix only costs
    thread start-up (and contention on a busy machine)."""
    return vectors[:, 0:1] * M[:, 0] + vectors[:, 1:2] * M[:, 1] + vectors[:, 2:3] * M[:, 2]


def project(K: np.ndarray, T_cw: np.ndarray, points_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (M, 2) and depths (M,) of world points in a camera; pixels are NaN behind the camera."""
    camera = transform(T_cw, points_w)
    depth = camera[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = camera[:, :2] / np.where(depth > 0, depth, np.nan)[:, None]
    return uv * K[[0, 1], [0, 1]] + K[:2, 2], depth


def projection_jacobian(K: np.ndarray, camera_points: np.ndarray) -> np.ndarray:
    """(M, 2, 6) derivative of the pixels of camera-frame points with respect to a perturbation
    (rotation w, translation v) of the camera frame that moves each point as dX = w x X + v."""
    x, y, z = camera_points.T
    zeros = np.zeros_like(z)
    pixel = np.stack(
        [
            np.column_stack([K[0, 0] / z, zeros, -K[0, 0] * x / z**2]),
            np.column_stack([zeros, K[1, 1] / z, -K[1, 1] * y / z**2]),
        ],
        axis=1,
    )
    # w x X = -[X]x w
    minus_skew = np.zeros((len(z), 3, 3))
    minus_skew[:, 0, 1], minus_skew[:, 0, 2], minus_skew[:, 1, 2] = z, -y, x
    minus_skew[:, 1, 0], minus_skew[:, 2, 0], minus_skew[:, 2, 1] = -z, y, -x
    return np.concatenate([pixel @ minus_skew, pixel], axis=2)


def relative_centre_sigma(K: np.ndarray, T_cw: np.ndarray, points_w: np.ndarray, sigmas: np.ndarray) -> float:
    """Standard deviation of the camera centre that PnP from these points fixes (Gauss-Newton
    covariance of the pose from pixels with ``sigmas``), over the points' median depth. Points in
    a narrow strip of the view let rotation and translation trade off: the centre is then poorly
    fixed even by many points. Infinite when the points do not fix the pose at all."""
    camera = transform(T_cw, points_w)
    z = camera[:, 2]
    if len(z) < 3 or not (z > 0).all():
        return float("inf")
    jacobian = (projection_jacobian(K, camera) / sigmas[:, None, None]).reshape(-1, 6)
    information = jacobian.T @ jacobian
    if np.linalg.cond(information) > 1e12:
        return float("inf")
    # The centre moves by -R^T v: its spread is the translation block's.
    covariance = np.linalg.inv(information)
    return float(np.sqrt(np.trace(covariance[3:, 3:])) / np.median(z))


def triangulate(
    K: np.ndarray, T1_cw: np.ndarray, T2_cw: np.ndarray, x1: np.ndarray, x2: np.ndarray
) -> np.ndarray:
    """World points (M, 3) from pixel matches in two cameras (linear DLT)."""
    if len(x1) == 0:
        return np.zeros((0, 3))
    homogeneous = cv2.triangulatePoints(
        K @ T1_cw[:3], K @ T2_cw[:3], x1.T.astype(np.float64), x2.T.astype(np.float64)
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        return (homogeneous[:3] / homogeneous[3]).T


def check_triangulated(
    K: np.ndarray,
    poses_cw: tuple[np.ndarray, np.ndarray],
    pixels: tuple[np.ndarray, np.ndarray],
    points_w: np.ndarray,
    max_error: np.ndarray | float,
    min_parallax_deg: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Which points are in front of both cameras, reproject within ``max_error`` and have parallax.

    Returns the mask and each point's parallax angle (deg).
    """
    good = np.isfinite(points_w).all(axis=1)
    for T_cw, x in zip(poses_cw, pixels, strict=True):
        uv, depth = project(K, T_cw, points_w)
        error = np.linalg.norm(uv - x, axis=1)
        good &= (depth > 0) & (np.nan_to_num(error, nan=np.inf) < max_error)
    rays = [points_w - invert(T)[:3, 3] for T in poses_cw]
    norms = np.linalg.norm(rays[0], axis=1) * np.linalg.norm(rays[1], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cosine = np.einsum("ij,ij->i", rays[0], rays[1]) / norms
    parallax = np.degrees(np.arccos(np.clip(np.nan_to_num(cosine, nan=1.0), -1.0, 1.0)))
    return good & (parallax >= min_parallax_deg), parallax


def fundamental_from_poses(K: np.ndarray, T1_cw: np.ndarray, T2_cw: np.ndarray) -> np.ndarray:
    """F with x2^T F x1 = 0 for pixels x1 in camera 1 and x2 in camera 2."""
    T21 = T2_cw @ invert(T1_cw)
    t = T21[:3, 3]
    skew = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    K_inv = np.linalg.inv(K)
    return K_inv.T @ skew @ T21[:3, :3] @ K_inv


def epipolar_distance(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Distance (px) of x2 from the epipolar line of x1."""
    lines = linear_map(F, np.column_stack([x1, np.ones(len(x1))]))
    residual = lines[:, 0] * x2[:, 0] + lines[:, 1] * x2[:, 1] + lines[:, 2]
    return np.abs(residual) / np.maximum(np.hypot(lines[:, 0], lines[:, 1]), 1e-12)
