"""Plain inputs without a dataset layout: a folder of images, or a video file.

Both need intrinsics: ``--calib`` or a YAML found next to the images (``intrinsics.yaml``, ... in
the folder; ``<video stem>.yaml`` or ``intrinsics.yaml`` ... beside a video). Without one they fail
with a ``CalibrationError`` asking for ``--calib``: a guessed focal length would silently distort
the map. Neither has ground truth.

Image folder: the image files directly in the folder. Timestamps, first match wins:
- ``times.txt`` in the folder, one time (s) per image in name order;
- file names that are decimal numbers with a fraction (``1341847980.722988.png``, TUM-style) are
  seconds; the frames are then ordered by that time rather than by name;
- otherwise the frames are in name order, ``1/30`` s apart. Integer names (``000042.png``) count
  as frame numbers, not seconds.

Video: frames are decoded in order with OpenCV while iterating (a video whose path is not UTF-8 is
refused with a ``DatasetError``: OpenCV's video reader crashes on such a name). Timestamps are
``index / fps`` (``CAP_PROP_FPS``; 30 when the file reports none). The frame count is the container's
(``CAP_PROP_FRAME_COUNT``, counted by grabbing every frame when it reports none); frames it
announces that do not decode are recorded in ``skipped``. ``read_image(i)`` seeks with
``CAP_PROP_POS_FRAMES``, which is slow and can land near rather than on frame i with inter-frame
codecs: iterate instead of indexing wherever possible.
"""

from __future__ import annotations

import itertools
import logging
import math
import os
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from frontends.datasets.base import (
    Dataset,
    ImageEntry,
    SkippedFrame,
    check_camera_size,
    display_path,
    first_image_size,
    list_images,
)
from frontends.datasets.calib import find_intrinsics_file, read_intrinsics
from frontends.errors import CalibrationError, DatasetError
from frontends.trajectory_io import read_times
from frontends.types import CameraIntrinsics, Frame

log = logging.getLogger(__name__)

#: Frame rate assumed when neither times.txt, file names nor the video give one.
DEFAULT_FPS = 30.0
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v")


def _camera(calib: Path | None, found: Path | None, size: tuple[int, int], where: Path) -> CameraIntrinsics:
    path = calib or found
    if path is None:
        raise CalibrationError(
            display_path(where),
            "no camera intrinsics: pass --calib intrinsics.yaml (fx fy cx cy width height distortion)",
        )
    return check_camera_size(read_intrinsics(path, size), size, where)


def _name_timestamp(path: Path) -> float | None:
    """The time a file name gives (``1341847980.722988.png``), or None for other names."""
    if "." not in path.stem:
        return None
    try:
        stamp = float(path.stem)
    except ValueError:
        return None
    return stamp if math.isfinite(stamp) else None


class ImageFolderDataset(Dataset):
    format_name = "folder"

    @staticmethod
    def detect(root: Path) -> bool:
        return root.is_dir() and bool(list_images(root))

    @classmethod
    def open(cls, root: Path, *, calib: Path | None = None, strict: bool = False) -> ImageFolderDataset:
        images = list_images(root)
        if not images:
            raise DatasetError(display_path(root), "no image files in this folder")
        notes: list[str] = []
        times_file = root / "times.txt"
        name_stamps = [s for s in (_name_timestamp(p) for p in images) if s is not None]
        if times_file.is_file():
            stamps = read_times(times_file, DatasetError)
            if len(stamps) != len(images):
                raise DatasetError(
                    display_path(times_file),
                    f"{len(stamps)} timestamps but {len(images)} images in {display_path(root)}",
                )
            entries = [ImageEntry(float(t), p) for t, p in zip(stamps, images, strict=True)]
        elif len(name_stamps) == len(images):
            by_time = sorted(zip(name_stamps, images, strict=True))
            entries = [ImageEntry(s, p) for s, p in by_time]
            for previous, entry in itertools.pairwise(entries):
                if entry.timestamp == previous.timestamp:
                    raise DatasetError(
                        display_path(entry.path),
                        f"same file-name timestamp as {display_path(previous.path.name)}",
                    )
            notes.append("timestamps from the file names (s)")
        else:
            entries = [ImageEntry(i / DEFAULT_FPS, p) for i, p in enumerate(images)]
            notes.append(f"no times.txt and file names are not timestamps: frames 1/{DEFAULT_FPS:g} s apart")
        size = first_image_size(entries)
        camera = _camera(calib, find_intrinsics_file(root), size, root)
        return cls(root, camera, entries, strict=strict, notes=notes)


class VideoDataset(Dataset):
    format_name = "video"

    @staticmethod
    def detect(root: Path) -> bool:
        return root.is_file() and root.suffix.lower() in VIDEO_SUFFIXES

    @classmethod
    def open(cls, root: Path, *, calib: Path | None = None, strict: bool = False) -> VideoDataset:
        notes: list[str] = []
        capture = cls._capture(root)
        try:
            fps = capture.get(cv2.CAP_PROP_FPS)
            count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
            ok, first = capture.read()
            if not ok or first is None:
                raise DatasetError(root, "the first video frame does not decode")
            if count <= 0:  # some containers do not store it: count by grabbing (no full decode)
                count = 1
                while capture.grab():
                    count += 1
                notes.append(f"the video does not report its frame count: counted {count} frames")
        finally:
            capture.release()
        if not math.isfinite(fps) or fps <= 0:
            fps = DEFAULT_FPS
            notes.append(f"the video reports no frame rate: assumed {DEFAULT_FPS:g} fps")
        size = (first.shape[1], first.shape[0])
        found = next((p for p in (root.with_suffix(".yaml"), root.with_suffix(".yml")) if p.is_file()), None)
        camera = _camera(calib, found or find_intrinsics_file(root.parent), size, root)
        entries = [ImageEntry(i / fps, root) for i in range(count)]
        return cls(root, camera, entries, strict=strict, notes=notes)

    @staticmethod
    def _capture(path: Path) -> cv2.VideoCapture:
        try:
            name = os.fsencode(path).decode("utf-8")
        except UnicodeDecodeError:  # cv2.VideoCapture crashes the process on such a name
            raise DatasetError(
                display_path(path),
                "OpenCV cannot open a video whose path is not UTF-8: rename it or link it under a UTF-8 name",
            ) from None
        capture = cv2.VideoCapture(name)
        if not capture.isOpened():
            capture.release()
            raise DatasetError(path, "OpenCV cannot open this video (unsupported codec or not a video)")
        return capture

    def __iter__(self) -> Iterator[Frame]:
        capture = self._capture(self.root)
        try:
            for index in range(len(self)):
                ok, image = capture.read()
                if not ok or image is None:
                    self._skip_rest(index)
                    return
                yield self._frame(index, image)
        finally:
            capture.release()

    def _skip_rest(self, first: int) -> None:
        """Frames announced by the container but not decoded: one warning, each recorded as skipped."""
        reason = f"video ended after {first} of {len(self)} announced frames"
        if self.strict:
            raise DatasetError(self.root, reason)
        log.warning("%s: %s; the rest are skipped", self.root, reason)
        self.skipped += [
            SkippedFrame(i, f"{self.root} frame {i}", reason, "video ended") for i in range(first, len(self))
        ]

    def read_image(self, index: int) -> np.ndarray | None:
        """Frame ``index`` by seeking (slow; see the module notes); a failure is recorded as skipped."""
        capture = self._capture(self.root)
        try:
            capture.set(cv2.CAP_PROP_POS_FRAMES, index)
            ok, image = capture.read()
        finally:
            capture.release()
        if not ok or image is None:
            self._skip(index, f"{self.root} frame {index}", "frame does not decode", "undecodable image")
            return None
        return image
