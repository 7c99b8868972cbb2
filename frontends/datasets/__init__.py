"""Dataset readers: TUM RGB-D, KITTI odometry (official and clip layouts), EuRoC MAV, image folder,
video file and loop-pairs sets. Every reader streams images and yields ``frontends.types.Frame``.

``open_dataset(path)`` picks the reader by ``fmt`` or by detecting the on-disk layout. Readers of
other packages register through the entry-point group ``symbio.datasets``. It first checks that the
dataset path and ``calib`` can be reached (not missing, not a symbolic link loop; ``calib`` a file),
so those are one clear error rather than a traceback from the first reader that touches them.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path
from typing import Protocol

from frontends.datasets.base import Dataset
from frontends.errors import CalibrationError, DatasetError, InputFileError, display_path
from frontends.registry import Registry


class DatasetReader(Protocol):
    format_name: str

    @staticmethod
    def detect(root: Path) -> bool: ...

    @classmethod
    def open(cls, root: Path, *, calib: Path | None = None, strict: bool = False) -> Dataset: ...


#: In detection order: the most specific layouts first.
DATASET_FORMATS: Registry[DatasetReader] = Registry(
    "dataset format",
    "symbio.datasets",
    {
        "euroc": "frontends.datasets.euroc:EurocDataset",
        "kitti": "frontends.datasets.kitti:KittiDataset",
        "loops": "frontends.datasets.loop_pairs:LoopPairsDataset",
        "tum": "frontends.datasets.tum:TumDataset",
        "video": "frontends.datasets.folder:VideoDataset",
        "folder": "frontends.datasets.folder:ImageFolderDataset",
    },
)


def detect_format(path: Path) -> str:
    builtin_order = ["euroc", "kitti", "loops", "tum", "video", "folder"]
    names = builtin_order + [n for n in DATASET_FORMATS.names() if n not in builtin_order]
    for name in names:
        if DATASET_FORMATS.load(name).detect(path):
            return name
    raise DatasetError(display_path(path), f"unrecognised dataset layout; pass --format ({', '.join(names)})")


#: ``unreachable_reason`` of a symbolic link loop.
SYMLINK_LOOP = "symbolic link loop (a link that leads back to itself)"


def unreachable_reason(path: Path, *, file: bool = False) -> str | None:
    """Why ``path`` cannot be read as an input (None when it can): not found, a symbolic link loop,
    not accessible or, with ``file``, a folder."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "not found"
    except OSError as exc:
        if exc.errno == errno.ELOOP:  # pathlib's exists() says False here and resolve() raises
            return SYMLINK_LOOP
        return f"cannot be read ({exc.strerror})"
    except ValueError:  # a NUL byte, which no path holds
        return "not found"
    if file and stat.S_ISDIR(mode):  # pipes stay allowed: --calib <(...)
        return "is a folder, not a file"
    return None


def check_input_path(path: Path, error: type[InputFileError], *, file: bool = False) -> None:
    """Raise ``error`` naming ``path`` when ``unreachable_reason`` finds one."""
    reason = unreachable_reason(path, file=file)
    if reason is not None:
        raise error(display_path(path), reason)


def open_dataset(
    path: str | Path, fmt: str | None = None, *, calib: str | Path | None = None, strict: bool = False
) -> Dataset:
    """Open a dataset folder (or video file) with the reader for ``fmt`` or the detected layout."""
    root = Path(path)
    check_input_path(root, DatasetError)
    calib_path = Path(calib) if calib is not None else None
    if calib_path is not None:
        check_input_path(calib_path, CalibrationError, file=True)
    name = fmt or detect_format(root)
    reader = DATASET_FORMATS.load(name)
    return reader.open(root, calib=calib_path, strict=strict)


__all__ = [
    "DATASET_FORMATS",
    "SYMLINK_LOOP",
    "Dataset",
    "DatasetReader",
    "check_input_path",
    "detect_format",
    "open_dataset",
    "unreachable_reason",
]
