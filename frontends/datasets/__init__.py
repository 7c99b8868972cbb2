"""Dataset readers: TUM RGB-D, KITTI odometry (official and clip layouts), EuRoC MAV, image folder,
video file and loop-pairs sets. Every reader streams images and yields ``frontends.types.Frame``.

``open_dataset(path)`` picks the reader by ``fmt`` or by detecting the on-disk layout. Readers of
other packages register through the entry-point group ``symbio.datasets``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

from frontends.datasets.base import Dataset
from frontends.errors import DatasetError
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
    raise DatasetError(path, f"unrecognised dataset layout; pass --format ({', '.join(names)})")


def open_dataset(
    path: str | Path, fmt: str | None = None, *, calib: str | Path | None = None, strict: bool = False
) -> Dataset:
    """Open a dataset folder (or video file) with the reader for ``fmt`` or the detected layout."""
    root = Path(path)
    if not root.exists():
        raise DatasetError(root, "not found")
    name = fmt or detect_format(root)
    reader = DATASET_FORMATS.load(name)
    return reader.open(root, calib=Path(calib) if calib is not None else None, strict=strict)


__all__ = ["DATASET_FORMATS", "Dataset", "DatasetReader", "detect_format", "open_dataset"]
