"""Loop-closure benchmark sets: ``images/`` plus ``gt_loop_pairs.txt``, no poses.

``gt_loop_pairs.txt`` holds ``query ref`` lines of 0-based indices into ``images/`` sorted by name
(``#`` comments allowed); indices are checked against the image count.

Such sets carry no times, so frame i is at i seconds. They rarely carry a calibration either:
``--calib`` or an intrinsics YAML in the folder is used when present, else the camera is estimated
as a pinhole with a 60 degree horizontal field of view (fx = fy = w / (2 tan 30deg), principal point
at the image centre) and ``camera.source`` says "estimated". Appearance-only loop detection does
not depend on it; geometric verification does, loosely.
"""

from __future__ import annotations

import math
from pathlib import Path

from frontends.datasets.base import (
    Dataset,
    ImageEntry,
    check_camera_size,
    display_path,
    first_image_size,
    list_images,
)
from frontends.datasets.calib import find_intrinsics_file, read_intrinsics
from frontends.errors import DatasetError
from frontends.gt_loops import read_loop_pairs
from frontends.types import CameraIntrinsics

LOOP_PAIRS_FILE = "gt_loop_pairs.txt"
#: Horizontal field of view assumed when there is no calibration (deg).
ESTIMATED_HFOV_DEG = 60.0


def estimated_camera(width: int, height: int) -> CameraIntrinsics:
    focal = width / (2.0 * math.tan(math.radians(ESTIMATED_HFOV_DEG) / 2.0))
    source = f"estimated from a {ESTIMATED_HFOV_DEG:g} deg horizontal field of view (pass --calib)"
    return CameraIntrinsics(focal, focal, width / 2.0, height / 2.0, width, height, (), source)


class LoopPairsDataset(Dataset):
    format_name = "loops"

    @staticmethod
    def detect(root: Path) -> bool:
        return (root / "images").is_dir() and (root / LOOP_PAIRS_FILE).is_file()

    @classmethod
    def open(cls, root: Path, *, calib: Path | None = None, strict: bool = False) -> LoopPairsDataset:
        images = list_images(root / "images")
        if not images:
            raise DatasetError(display_path(root / "images"), "no images")
        entries = [ImageEntry(float(i), path) for i, path in enumerate(images)]
        notes = ["no timestamps in this layout: frame i is at i s"]
        size = first_image_size(entries)
        intrinsics_file = calib or find_intrinsics_file(root)
        if intrinsics_file is not None:
            camera = check_camera_size(read_intrinsics(intrinsics_file, size), size, root)
        else:
            camera = estimated_camera(*size)
            notes.append(f"intrinsics {camera.source}")
        pairs = read_loop_pairs(root / LOOP_PAIRS_FILE, len(entries))
        return cls(root, camera, entries, gt_loop_pairs=pairs, strict=strict, notes=notes)
