"""KITTI odometry: the official sequence layout and flat clips.

Official layout (pass the sequence folder ``.../sequences/NN``): ``image_0/`` (grey left, used by
default) or ``image_2/`` (colour left), ``times.txt``, ``calib.txt`` and, for sequences 00-10 only,
ground truth in ``../../poses/NN.txt``. Passing the folder that contains ``sequences/`` is an error
that says which folder to pass instead.

Flat clip layout: ``image_l/``, ``image_0/`` or ``image_2/`` (checked in the order image_0, image_l,
image_2), ``calib.txt``, ``poses.txt`` and optionally ``times.txt``.

``calib.txt`` lines are 12 numbers (a 3x4 projection matrix, row-major), either prefixed with a
key (``P0: ...``, as KITTI ships them) or bare, in which case line k is ``P<k-1>``. The left camera
uses P0 (``image_0``/``image_l``) or P2 (``image_2``); KITTI images are rectified, so the camera has
no distortion. The matrix used must be ``K [I | t]`` with ``K`` upper triangular without skew:
rows ``fx 0 cx tx``, ``0 fy cy ty``, ``0 0 1 tz`` (``P0`` has ``t = 0``; the other cameras of a rig
have their baseline there, which monocular intrinsics do not use, so ``t`` is not checked).
Anything else (skew, a rotated or scaled third row) is a ``CalibrationError`` naming the line.
``--calib`` replaces calib.txt. Without ``times.txt`` frames are 0.1 s apart (KITTI's 10 Hz).
Poses are camera-to-world, one line per image.
"""

from __future__ import annotations

import reprlib
from pathlib import Path

import numpy as np

from frontends.datasets.base import (
    Dataset,
    ImageEntry,
    check_camera_size,
    display_path,
    first_image_size,
    list_images,
)
from frontends.datasets.calib import read_intrinsics
from frontends.errors import CalibrationError, DatasetError
from frontends.trajectory_io import read_kitti_poses, read_times
from frontends.types import CameraIntrinsics

#: Image folders in the order they are looked for, with the projection matrix of each camera.
IMAGE_FOLDERS = {"image_0": "P0", "image_l": "P0", "image_2": "P2"}
#: KITTI's camera rate, used when there is no times.txt.
KITTI_FPS = 10.0
#: Largest entry allowed where a pinhole projection matrix has 0 (skew, below the diagonal, third
#: row), relative to the focal length; KITTI writes exact zeros.
PROJECTION_TOLERANCE = 1e-6


def read_projection_matrices(path: Path) -> dict[str, np.ndarray]:
    """The 3x4 matrices of a KITTI ``calib.txt``, by key (``P0`` ...); bare lines are numbered."""
    return {key: matrix for key, (matrix, _) in _read_projections(path).items()}


def _read_projections(path: Path) -> dict[str, tuple[np.ndarray, int]]:
    """``read_projection_matrices`` with the line of each matrix."""
    try:
        lines = path.read_text(encoding="utf-8-sig").splitlines()
    except FileNotFoundError:
        raise CalibrationError(path, "not found (pass --calib intrinsics.yaml instead)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(path, f"cannot read file ({exc})") from None
    matrices: dict[str, tuple[np.ndarray, int]] = {}
    for number, raw in enumerate(lines, start=1):
        fields = raw.split()
        if not fields or fields[0].startswith("#"):
            continue
        key = fields[0].rstrip(":") if fields[0].endswith(":") else f"P{len(matrices)}"
        values = fields[1:] if fields[0].endswith(":") else fields
        if len(values) != 12:
            raise CalibrationError(path, f"{key}: expected 12 numbers, found {len(values)}", number)
        try:
            matrix = np.array([float(v) for v in values]).reshape(3, 4)
        except ValueError:
            raise CalibrationError(path, f"{key}: not a number in {reprlib.repr(values)}", number) from None
        if not np.isfinite(matrix).all():
            raise CalibrationError(path, f"{key}: non-finite value", number)
        matrices[key] = (matrix, number)
    return matrices


def check_pinhole_projection(path: Path, key: str, matrix: np.ndarray, line: int) -> None:
    """Raise naming ``line`` unless ``matrix`` is ``K [I | t]`` with ``K`` = [[fx 0 cx] [0 fy cy] [0 0 1]]."""
    fx, fy = float(matrix[0, 0]), float(matrix[1, 1])
    if fx <= 0 or fy <= 0:
        raise CalibrationError(path, f"{key}: focal lengths must be positive, got fx={fx:g}, fy={fy:g}", line)
    scale = max(fx, fy)
    problems = []
    if abs(matrix[0, 1]) > PROJECTION_TOLERANCE * scale:
        problems.append(f"skew {matrix[0, 1]:g} (row 1, column 2)")
    if abs(matrix[1, 0]) > PROJECTION_TOLERANCE * scale:
        problems.append(f"{matrix[1, 0]:g} below the diagonal (row 2, column 1)")
    if np.abs(matrix[2, :3] - [0.0, 0.0, 1.0]).max() > PROJECTION_TOLERANCE:
        problems.append(f"third row starts {' '.join(f'{v:g}' for v in matrix[2, :3])}, not 0 0 1")
    if problems:
        raise CalibrationError(
            path,
            f"{key} is not a rectified pinhole projection [fx 0 cx tx; 0 fy cy ty; 0 0 1 tz]: "
            + "; ".join(problems),
            line,
        )


def _image_folder(root: Path) -> Path:
    for name in IMAGE_FOLDERS:
        if (root / name).is_dir():
            return root / name
    names = ", ".join(f"{name}/" for name in IMAGE_FOLDERS)
    raise DatasetError(display_path(root), f"no image folder ({names}): not a KITTI sequence")


def _poses_file(root: Path) -> Path | None:
    """``poses.txt`` of a clip, else ``../../poses/NN.txt`` of an official sequence, else None."""
    root = root.resolve()  # so that "." still has a name and parents
    if (root / "poses.txt").is_file():
        return root / "poses.txt"
    official = root.parent.parent / "poses" / f"{root.name}.txt"
    return official if root.parent.name == "sequences" and official.is_file() else None


def _check_count(path: Path, count: int, what: str, folder: Path, images: int) -> None:
    if count != images:
        raise DatasetError(
            display_path(path),
            f"{count} {what} (one per line) but {images} images in {display_path(folder.name)}/",
        )


class KittiDataset(Dataset):
    format_name = "kitti"

    @staticmethod
    def detect(root: Path) -> bool:
        # A folder holding sequences/ is claimed too, so that open() can say which folder to pass.
        if (root / "sequences").is_dir():
            return True
        return (root / "calib.txt").is_file() and any((root / name).is_dir() for name in IMAGE_FOLDERS)

    @classmethod
    def open(cls, root: Path, *, calib: Path | None = None, strict: bool = False) -> KittiDataset:
        if (root / "sequences").is_dir() and not (root / "calib.txt").is_file():
            raise DatasetError(
                display_path(root), "this is the KITTI dataset root: pass one sequence, e.g. sequences/00"
            )
        folder = _image_folder(root)
        images = list_images(folder)
        if not images:
            raise DatasetError(display_path(folder), "no images")
        notes = [f"images: {folder.name}/"]

        times_file = root / "times.txt"
        if times_file.is_file():
            stamps = read_times(times_file, DatasetError)
            _check_count(times_file, len(stamps), "timestamps", folder, len(images))
        else:
            stamps = np.arange(len(images)) / KITTI_FPS
            notes.append(f"no times.txt: frames {1 / KITTI_FPS:g} s apart (KITTI's {KITTI_FPS:g} Hz)")
        entries = [ImageEntry(float(t), path) for t, path in zip(stamps, images, strict=True)]

        size = first_image_size(entries)
        if calib is not None:
            camera = check_camera_size(read_intrinsics(calib, size), size, root)
        else:
            camera = cls._camera(root / "calib.txt", IMAGE_FOLDERS[folder.name], size)

        gt_poses = None
        poses_file = _poses_file(root)
        if poses_file is not None:
            poses = np.asarray(read_kitti_poses(poses_file).poses_se3)
            _check_count(poses_file, len(poses), "poses", folder, len(images))
            gt_poses = poses
        else:
            notes.append("no ground truth (poses.txt or ../../poses/NN.txt)")
        return cls(root, camera, entries, gt_poses=gt_poses, strict=strict, notes=notes)

    @staticmethod
    def _camera(calib_file: Path, key: str, size: tuple[int, int]) -> CameraIntrinsics:
        matrices = _read_projections(calib_file)
        if key not in matrices:
            names = [name if len(name) <= 12 else name[:9] + "..." for name in matrices]  # bounded message
            found = ", ".join(names[:8]) + (", ..." if len(names) > 8 else "") or "none"
            raise CalibrationError(calib_file, f"no {key} projection matrix (found: {found})")
        matrix, line = matrices[key]
        check_pinhole_projection(calib_file, key, matrix, line)
        fx, fy, cx, cy = (float(matrix[i, j]) for i, j in ((0, 0), (1, 1), (0, 2), (1, 2)))
        return CameraIntrinsics(fx, fy, cx, cy, size[0], size[1], (), f"{calib_file} {key}")
