"""TUM RGB-D layout: ``rgb.txt``, ``rgb/``, optional ``groundtruth.txt``.

Intrinsics, first match wins: an explicit ``--calib`` YAML, an intrinsics YAML in the folder
(synthetic scenes write one), the freiburg camera named by the folder (``freiburg1``/``fr1`` ...,
TUM's published calibration), else TUM's ROS default with a warning. Ground truth is associated
to each image by nearest timestamp within 0.02 s (TUM's ``associate.py`` tolerance).

Without ``rgb.txt`` (e.g. a clip of copied frames) the images in ``rgb/`` are used when their file
names are timestamps, which is how TUM names them. File names in ``rgb.txt`` that are not UTF-8
are kept as the bytes they are, so they name the files on disk.
"""

from __future__ import annotations

import logging
import re
import reprlib
from pathlib import Path

import numpy as np

from frontends.datasets.base import (
    Dataset,
    ImageEntry,
    associate_nearest,
    check_camera_size,
    check_listed_images_exist,
    display_path,
    first_image_size,
    list_images,
)
from frontends.datasets.calib import find_intrinsics_file, read_intrinsics
from frontends.errors import DatasetError
from frontends.gt_loops import read_loop_pairs
from frontends.trajectory_io import check_increasing, read_tum
from frontends.types import CameraIntrinsics

log = logging.getLogger(__name__)

#: TUM's published calibration of the three freiburg Kinects (fx, fy, cx, cy, k1, k2, p1, p2, k3).
FREIBURG_INTRINSICS = {
    1: (517.306408, 516.469215, 318.643040, 255.313989, (0.262383, -0.953104, -0.005358, 0.002628, 1.163314)),
    2: (
        520.908620,
        521.007327,
        325.141442,
        249.701764,
        (0.231222, -0.784899, -0.003257, -0.000105, 0.917205),
    ),
    # fr3 images were already undistorted by the Kinect driver (TUM: "use no distortion").
    3: (535.4, 539.2, 320.1, 247.6, ()),
}
ROS_DEFAULT_INTRINSICS = (525.0, 525.0, 319.5, 239.5, ())
#: Maximum image/ground-truth time difference for association (s).
MAX_GT_TIME_DIFFERENCE = 0.02

_FREIBURG_PATTERN = re.compile(r"(?:freiburg|fr)([123])(?![0-9])", re.IGNORECASE)


def freiburg_camera(root: Path) -> int | None:
    """The freiburg camera number named anywhere in the path (folder names carry it)."""
    for part in reversed(root.resolve().parts):
        match = _FREIBURG_PATTERN.search(part)
        if match:
            return int(match.group(1))
    return None


def _read_rgb_list(root: Path) -> list[ImageEntry]:
    index = root / "rgb.txt"
    entries: list[ImageEntry] = []
    shown = display_path(index)
    try:
        # surrogateescape: a name that is not UTF-8 becomes the str os.fsdecode gives the file.
        lines = index.read_text(encoding="utf-8-sig", errors="surrogateescape").splitlines()
    except OSError as exc:
        raise DatasetError(shown, f"cannot read ({exc.strerror})") from None
    for number, raw in enumerate(lines, start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        if len(fields) != 2:
            raise DatasetError(shown, f"expected 'timestamp filename', found {len(fields)} fields", number)
        try:
            stamp = float(fields[0])
        except ValueError:
            raise DatasetError(
                shown, f"timestamp is not a number: {reprlib.repr(fields[0])}", number
            ) from None
        if not np.isfinite(stamp):
            raise DatasetError(shown, f"timestamp is not finite: {reprlib.repr(fields[0])}", number)
        entries.append(ImageEntry(stamp, root / fields[1], index, number))
    if not entries:
        raise DatasetError(shown, "lists no images")
    stamps = np.array([e.timestamp for e in entries])
    check_increasing(shown, stamps, np.array([e.line for e in entries]), DatasetError)
    return entries


def _entries_from_file_names(root: Path) -> list[ImageEntry]:
    images = list_images(root / "rgb")
    entries = []
    for path in images:
        try:
            entries.append(ImageEntry(float(path.stem), path))
        except ValueError:
            raise DatasetError(
                display_path(path), "no rgb.txt and this file name is not a timestamp"
            ) from None
    if not entries:
        raise DatasetError(display_path(root / "rgb"), "no images")
    return entries


class TumDataset(Dataset):
    format_name = "tum"

    @staticmethod
    def detect(root: Path) -> bool:
        return (root / "rgb.txt").is_file() or ((root / "rgb").is_dir() and not (root / "images").is_dir())

    @classmethod
    def open(cls, root: Path, *, calib: Path | None = None, strict: bool = False) -> TumDataset:
        notes: list[str] = []
        if (root / "rgb.txt").is_file():
            entries = _read_rgb_list(root)
        elif (root / "rgb").is_dir():
            entries = _entries_from_file_names(root)
            notes.append("no rgb.txt: frames from rgb/ file names (timestamps)")
        else:
            raise DatasetError(
                display_path(root / "rgb.txt"), "not found (and no rgb/ folder): not a TUM RGB-D folder"
            )
        check_listed_images_exist(entries, strict)
        size = first_image_size(entries)
        camera = check_camera_size(cls._camera(root, calib, size, notes), size, root)

        gt_poses = None
        if (root / "groundtruth.txt").is_file():
            gt = read_tum(root / "groundtruth.txt")
            stamps = np.array([e.timestamp for e in entries])
            nearest = associate_nearest(stamps, gt.timestamps, MAX_GT_TIME_DIFFERENCE)
            poses = np.asarray(gt.poses_se3)
            gt_poses = np.full((len(entries), 4, 4), np.nan)
            gt_poses[nearest >= 0] = poses[nearest[nearest >= 0]]
            if (nearest < 0).any():
                notes.append(
                    f"{int((nearest < 0).sum())} frames have no ground truth within "
                    f"{MAX_GT_TIME_DIFFERENCE} s"
                )
        pairs = None
        if (root / "gt_loop_pairs.txt").is_file():
            pairs = read_loop_pairs(root / "gt_loop_pairs.txt", len(entries))
        return cls(root, camera, entries, gt_poses=gt_poses, gt_loop_pairs=pairs, strict=strict, notes=notes)

    @staticmethod
    def _camera(root: Path, calib: Path | None, size: tuple[int, int], notes: list[str]) -> CameraIntrinsics:
        explicit = calib or find_intrinsics_file(root)
        if explicit is not None:
            return read_intrinsics(explicit, size)
        number = freiburg_camera(root)
        if number is not None:
            fx, fy, cx, cy, dist = FREIBURG_INTRINSICS[number]
            source = f"TUM freiburg{number} calibration (from the folder name)"
        else:
            fx, fy, cx, cy, dist = ROS_DEFAULT_INTRINSICS
            source = "TUM ROS default (the folder name names no freiburg camera)"
            log.warning("%s: %s; pass --calib to set the intrinsics", display_path(root), source)
        notes.append(f"intrinsics: {source}")
        # The published values are for 640x480; scale if the images were resized.
        return CameraIntrinsics(fx, fy, cx, cy, 640, 480, dist, source).with_size(*size)
