"""Types shared by every package: camera, frame, detected object, keyframe, trajectory.

Trajectories are evo's ``PoseTrajectory3D`` (re-exported as ``Trajectory``) so that file I/O,
alignment and APE/RPE come from evo rather than from this project.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from evo.core.trajectory import PoseTrajectory3D

from frontends.errors import CalibrationError

Trajectory = PoseTrajectory3D

#: Distortion models OpenCV accepts: (k1, k2, p1, p2[, k3[, k4, k5, k6]]).
_VALID_DISTORTION_LENGTHS = (0, 4, 5, 8)


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole camera with OpenCV radial-tangential distortion (k1, k2, p1, p2[, k3])."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, ...] = ()
    #: Where these values came from (a file, a dataset's published calibration, an estimate).
    source: str = ""

    def __post_init__(self) -> None:
        where = self.source or "camera intrinsics"
        values = (self.fx, self.fy, self.cx, self.cy, *self.distortion)
        if not all(math.isfinite(v) for v in values):
            raise CalibrationError(where, f"intrinsics must be finite numbers, got {values}")
        if self.fx <= 0 or self.fy <= 0:
            raise CalibrationError(where, f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(where, f"image size must be positive, got {self.width}x{self.height}")
        if len(self.distortion) not in _VALID_DISTORTION_LENGTHS:
            raise CalibrationError(
                where,
                f"distortion must have 0, 4, 5 or 8 coefficients (k1 k2 p1 p2 [k3 ...]), "
                f"got {len(self.distortion)}",
            )

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_coeffs(self) -> np.ndarray:
        return np.asarray(self.distortion, dtype=np.float64)

    @property
    def is_distorted(self) -> bool:
        return any(abs(d) > 0 for d in self.distortion)

    def undistort(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) pixel positions in the undistorted image (float64)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if not self.is_distorted or len(xy) == 0:
            return xy
        K = self.K
        return cv2.undistortPoints(xy.reshape(-1, 1, 2), K, self.dist_coeffs, P=K).reshape(-1, 2)

    def with_size(self, width: int, height: int) -> CameraIntrinsics:
        """The same camera for an image resized to ``width`` x ``height``."""
        sx, sy = width / self.width, height / self.height
        return CameraIntrinsics(
            self.fx * sx,
            self.fy * sy,
            self.cx * sx,
            self.cy * sy,
            width,
            height,
            self.distortion,
            self.source,
        )

    def as_dict(self) -> dict[str, object]:
        return {
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "width": self.width,
            "height": self.height,
            "distortion": list(self.distortion),
        }


@dataclass(frozen=True)
class DetectedObject:
    """One object in an image: from a CNN detector, or ground truth from a synthetic scene."""

    label: str
    score: float
    #: Axis-aligned box (x0, y0, x1, y1) in pixels, x1/y1 exclusive.
    box: tuple[float, float, float, float]
    mask: np.ndarray | None = None
    #: Instance id when known (ground truth), else -1.
    instance: int = -1
    #: Fraction of the object's unoccluded in-image area that is visible (ground truth only).
    visible_fraction: float = 1.0


@dataclass(frozen=True)
class Frame:
    """One image of a sequence, loaded lazily by a dataset reader."""

    index: int
    timestamp: float
    image: np.ndarray
    path: str | None = None
    #: Ground-truth camera-to-world pose (4x4), when the dataset has one for this frame.
    gt_pose: np.ndarray | None = None

    @property
    def gray(self) -> np.ndarray:
        if self.image.ndim == 2:
            return self.image
        import cv2

        return cv2.cvtColor(self.image, cv2.COLOR_BGR2GRAY)


@dataclass
class Keyframe:
    """A frame the frontend kept: what the loop detector and the verifier consume."""

    id: int
    frame_index: int
    timestamp: float
    #: Camera-to-world pose (4x4). Monocular: in the map's arbitrary scale, a Sim(3) ``[s R, t]``
    #: once loop corrections have rescaled the map around the keyframe (``points3d`` then stay in
    #: the keyframe's own units: its camera frame divided by ``s``).
    pose: np.ndarray
    keypoints: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    descriptors: np.ndarray = field(default_factory=lambda: np.zeros((0, 32), np.uint8))
    objects: tuple[DetectedObject, ...] = ()
    image: np.ndarray | None = None
    #: (N, 3) map point of each keypoint in this keyframe's camera frame, NaN rows where a keypoint
    #: has none (what Sim(3) geometric verification aligns). None when the frontend has no map.
    points3d: np.ndarray | None = None
    #: (N,) map point id of each keypoint, -1 where none: two keyframes of one segment with the
    #: same id see the same point (what global bundle adjustment joins). None without a map.
    point_ids: np.ndarray | None = None
    #: Map segment: a new segment starts after a tracking loss that relocalisation could not
    #: recover; poses of different segments share no frame until a loop reconnects them.
    segment: int = 0
    #: (N,) standard deviation of each keypoint's position in pixels relative to the finest
    #: detection scale (ORB: the pyramid level's scale factor); None = all equal.
    keypoint_sigmas: np.ndarray | None = None
    #: Covariance of the motion from the previous keyframe of the segment (7x7 Sim(3) tangent order
    #: of ``slam_backend.lie``: rotation, translation, log-scale), None when unknown.
    odometry_covariance: np.ndarray | None = None
