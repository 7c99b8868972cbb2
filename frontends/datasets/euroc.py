"""EuRoC MAV (ASL) layout: pass the sequence folder holding ``mav0/`` (or ``mav0/`` itself).

- Images: ``mav0/cam0/data.csv`` (``#timestamp [ns],filename``) lists ``mav0/cam0/data/*.png``;
  nanosecond timestamps become float seconds and must be strictly increasing.
- Intrinsics: ``mav0/cam0/sensor.yaml`` (Kalibr: ``intrinsics``, radial-tangential
  ``distortion_coefficients`` k1 k2 p1 p2 kept as is, ``resolution``); ``--calib`` overrides them.
- Ground truth (optional): ``mav0/state_groundtruth_estimate0/data.csv``, whose first 8 columns are
  timestamp (ns), body position p_RS_R and orientation q_RS (w x y z); EuRoC adds velocities and
  biases (17 columns). A repeated timestamp keeps its first row, as for TUM ground truth. The
  camera pose is ``T_WB @ T_BS`` with ``T_BS`` (body -> camera) from sensor.yaml; without
  sensor.yaml (``--calib`` given) T_BS is the identity, noted in ``notes``. ``T_BS`` must be
  rigid: last row ``0 0 0 1`` and a rotation with ``R Rᵀ = I`` and ``det R = +1`` within
  ``T_BS_TOLERANCE`` (Kalibr prints about 10 digits). Each image takes the nearest ground-truth
  sample within 0.01 s (the ground truth is 200 Hz).
"""

from __future__ import annotations

import re
import reprlib
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from frontends.datasets.base import (
    Dataset,
    ImageEntry,
    associate_nearest,
    check_camera_size,
    check_listed_images_exist,
    display_path,
    first_image_size,
)
from frontends.datasets.calib import intrinsics_from_mapping, read_intrinsics, read_yaml_file
from frontends.errors import CalibrationError, DatasetError, TrajectoryFileError
from frontends.trajectory_io import check_increasing, drop_duplicate_stamps, read_numeric_table
from frontends.types import CameraIntrinsics

#: Maximum image/ground-truth time difference for association (s).
MAX_GT_TIME_DIFFERENCE = 0.01
#: Largest deviation of T_BS's rotation from orthonormal (max |R Rᵀ - I|, |det R - 1|).
T_BS_TOLERANCE = 1e-3
GROUNDTRUTH_CSV = Path("state_groundtruth_estimate0") / "data.csv"


def mav0_folder(root: Path) -> Path | None:
    for candidate in (root / "mav0", root):
        if (candidate / "cam0" / "data.csv").is_file():
            return candidate
    return None


def read_image_list(csv: Path) -> list[ImageEntry]:
    """``data.csv`` of a camera: ``timestamp_ns,filename`` lines, images in the sibling ``data/``."""
    shown = display_path(csv)
    try:
        # surrogateescape: a name that is not UTF-8 becomes the str os.fsdecode gives the file.
        lines = csv.read_text(encoding="utf-8-sig", errors="surrogateescape").splitlines()
    except OSError as exc:
        raise DatasetError(shown, f"cannot read ({exc.strerror})") from None
    entries: list[ImageEntry] = []
    for number, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = [f.strip() for f in line.split(",")]
        if len(fields) != 2 or not fields[1]:
            raise DatasetError(shown, f"expected 'timestamp_ns,filename', found {reprlib.repr(line)}", number)
        try:
            stamp_ns = int(fields[0])
        except ValueError:
            raise DatasetError(
                shown, f"timestamp is not an integer (ns): {reprlib.repr(fields[0])}", number
            ) from None
        entries.append(ImageEntry(stamp_ns * 1e-9, csv.parent / "data" / fields[1], csv, number))
    if not entries:
        raise DatasetError(shown, "lists no images")
    stamps = np.array([e.timestamp for e in entries])
    check_increasing(shown, stamps, np.array([e.line for e in entries]), DatasetError)
    return entries


def _key_line(path: Path, key: str) -> int | None:
    """The 1-based line where ``key:`` starts a line of the YAML file (for error messages)."""
    pattern = re.compile(rf"{re.escape(key)}\s*:")  # top level: not indented
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError:
        return None
    return next((number for number, line in enumerate(lines, start=1) if pattern.match(line)), None)


def read_body_to_sensor(sensor_yaml: Path) -> np.ndarray:
    """``T_BS`` of a Kalibr sensor.yaml (``{cols: 4, rows: 4, data: [16 numbers]}``), checked rigid."""
    value = read_yaml_file(sensor_yaml).get("T_BS")
    data = value.get("data") if isinstance(value, dict) else value
    line = _key_line(sensor_yaml, "T_BS")
    if not isinstance(data, list) or len(data) != 16:
        raise CalibrationError(
            sensor_yaml, f"T_BS must be a 4x4 matrix (16 numbers in 'data'): {reprlib.repr(value)}", line
        )
    try:
        matrix = np.array([float(v) for v in data]).reshape(4, 4)
    except (TypeError, ValueError, OverflowError):
        raise CalibrationError(
            sensor_yaml, f"T_BS has a value that is not a number: {reprlib.repr(data)}", line
        ) from None
    if not np.isfinite(matrix).all() or not np.allclose(matrix[3], [0, 0, 0, 1]):
        rows = np.array2string(matrix, precision=6, separator=" ", max_line_width=200)
        raise CalibrationError(
            sensor_yaml, f"T_BS is not a rigid transform (last row must be 0 0 0 1): {rows}", line
        )
    rotation = matrix[:3, :3]
    orthogonality = float(np.abs(rotation @ rotation.T - np.eye(3)).max())
    determinant = float(np.linalg.det(rotation))
    if orthogonality > T_BS_TOLERANCE or abs(determinant - 1.0) > T_BS_TOLERANCE:
        raise CalibrationError(
            sensor_yaml,
            f"T_BS is not a rigid transform: its rotation has max |R Rᵀ - I| = {orthogonality:.3g} and "
            f"det R = {determinant:.6g} (a rotation has 0 and +1, tolerance {T_BS_TOLERANCE:g})",
            line,
        )
    return matrix


def read_groundtruth(csv: Path) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (s) and body-to-world poses (N, 4, 4) of an EuRoC ground-truth csv."""
    table, lines = read_numeric_table(csv, (8, 17), TrajectoryFileError, delimiter=",")
    keep = drop_duplicate_stamps(csv, table[:, 0], lines)
    table, lines = table[keep], lines[keep]
    stamps = table[:, 0] * 1e-9
    quat_wxyz = table[:, 4:8]
    norms = np.linalg.norm(quat_wxyz, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-2)
    if bad.size:
        k = int(bad[0])
        raise TrajectoryFileError(csv, f"quaternion is not unit length (norm {norms[k]:.4f})", int(lines[k]))
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(quat_wxyz / norms[:, None], scalar_first=True).as_matrix()
    poses[:, :3, 3] = table[:, 1:4]
    return stamps, poses


class EurocDataset(Dataset):
    format_name = "euroc"

    @staticmethod
    def detect(root: Path) -> bool:
        return mav0_folder(root) is not None

    @classmethod
    def open(cls, root: Path, *, calib: Path | None = None, strict: bool = False) -> EurocDataset:
        mav0 = mav0_folder(root)
        if mav0 is None:
            raise DatasetError(
                display_path(root / "mav0" / "cam0" / "data.csv"), "not found: not a EuRoC sequence"
            )
        entries = read_image_list(mav0 / "cam0" / "data.csv")
        check_listed_images_exist(entries, strict)
        size = first_image_size(entries)
        notes: list[str] = []

        sensor_yaml = mav0 / "cam0" / "sensor.yaml"
        camera: CameraIntrinsics
        if calib is not None:
            camera = read_intrinsics(calib, size)
        elif sensor_yaml.is_file():
            camera = intrinsics_from_mapping(read_yaml_file(sensor_yaml), sensor_yaml, size)
        else:
            raise CalibrationError(display_path(sensor_yaml), "not found (pass --calib intrinsics.yaml)")
        camera = check_camera_size(camera, size, root)

        gt_poses = None
        gt_csv = mav0 / GROUNDTRUTH_CSV
        if gt_csv.is_file():
            if sensor_yaml.is_file():
                body_to_camera = read_body_to_sensor(sensor_yaml)
            else:
                body_to_camera = np.eye(4)
                notes.append(
                    f"{display_path(sensor_yaml)} not found: ground truth is the body pose (T_BS = identity)"
                )
            gt_stamps, body_poses = read_groundtruth(gt_csv)
            stamps = np.array([e.timestamp for e in entries])
            nearest = associate_nearest(stamps, gt_stamps, MAX_GT_TIME_DIFFERENCE)
            gt_poses = np.full((len(entries), 4, 4), np.nan)
            gt_poses[nearest >= 0] = body_poses[nearest[nearest >= 0]] @ body_to_camera
            if (nearest < 0).any():
                notes.append(
                    f"{int((nearest < 0).sum())} frames have no ground truth within "
                    f"{MAX_GT_TIME_DIFFERENCE} s"
                )
        else:
            notes.append(f"no ground truth ({display_path(gt_csv)} not found)")
        return cls(root, camera, entries, gt_poses=gt_poses, strict=strict, notes=notes)
