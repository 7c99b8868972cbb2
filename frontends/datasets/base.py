"""The dataset model every reader produces: a streamed image sequence with its camera.

Images are decoded one at a time while iterating, never all held in memory. An image that is
missing, fails to decode or has another size than the camera's is skipped with a warning and
recorded in ``Dataset.skipped`` (with the
index file and line that listed it); ``strict=True`` turns that into a ``DatasetError``. The
built-in readers reject index files whose timestamps do not increase when opening them; a frame
whose timestamp is not after the previous frame's (a reader that does not check, e.g. a plugin) is
skipped and recorded the same way, so a frontend never sees time run backwards.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import cv2
import numpy as np
from evo.core.trajectory import PoseTrajectory3D

from frontends.errors import CalibrationError, DatasetError
from frontends.gt_loops import LoopLabelConfig, label_loop_pairs
from frontends.types import CameraIntrinsics, Frame

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImageEntry:
    """One image of the sequence and where it was listed (for error messages)."""

    timestamp: float
    path: Path
    listed_in: Path | None = None
    line: int | None = None

    def where(self) -> str:
        if self.listed_in is None:
            return str(self.path)
        return f"{self.listed_in}:{self.line}" if self.line is not None else str(self.listed_in)


@dataclass(frozen=True)
class SkippedFrame:
    index: int
    where: str
    reason: str
    #: The reason's category, for counting: one of ``SKIP_CAUSES``.
    cause: str


SKIP_CAUSES = (
    "missing image",
    "undecodable image",
    "wrong image size",
    "duplicate timestamp",
    "backwards timestamp",
    "video ended",
)


def decode_image(path: Path) -> np.ndarray | None:
    """Read an image as 8-bit grey or BGR; None when it is missing or does not decode."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        return None
    if image.dtype == np.uint16:  # 16-bit PNG greyscale cameras: keep the high byte
        image = (image // 256).astype(np.uint8)
    elif image.dtype != np.uint8:
        return None
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    elif image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    return image


def associate_nearest(query: np.ndarray, reference: np.ndarray, max_difference: float) -> np.ndarray:
    """For each query stamp, the index of the nearest reference stamp within ``max_difference``, else -1.

    Same tolerance rule as TUM's ``associate.py`` (default 0.02 s), without its one-to-one constraint:
    ground truth is sampled much faster than images, so nearest-neighbour is what it picks anyway.
    """
    reference = np.asarray(reference, dtype=np.float64)
    if reference.size == 0:
        return np.full(len(query), -1, dtype=np.int64)
    right = np.clip(np.searchsorted(reference, query), 1, len(reference) - 1) if len(reference) > 1 else None
    if right is None:
        nearest = np.zeros(len(query), dtype=np.int64)
    else:
        left = right - 1
        nearest = np.where(np.abs(reference[left] - query) <= np.abs(reference[right] - query), left, right)
    return np.where(np.abs(reference[nearest] - query) <= max_difference, nearest, -1)


class Dataset:
    """A monocular image sequence: camera, timestamps, optional GT poses and GT loop pairs."""

    #: The name ``--format`` selects this reader by.
    format_name: ClassVar[str] = ""

    def __init__(
        self,
        root: Path,
        camera: CameraIntrinsics,
        entries: Sequence[ImageEntry],
        *,
        gt_poses: np.ndarray | None = None,
        gt_loop_pairs: np.ndarray | None = None,
        strict: bool = False,
        notes: Sequence[str] = (),
    ) -> None:
        self.root = root
        self.camera = camera
        self.entries = list(entries)
        self.timestamps = np.array([e.timestamp for e in self.entries], dtype=np.float64)
        #: Camera-to-world GT pose per frame, NaN where the frame has none; None without GT.
        self.gt_poses = gt_poses
        #: Loop pairs given by the dataset itself (a file), as opposed to computed from poses.
        self.gt_loop_pairs = gt_loop_pairs
        self.strict = strict
        #: Human-readable remarks from opening (fallbacks taken, assumptions made).
        self.notes = list(notes)
        self.skipped: list[SkippedFrame] = []
        if gt_poses is not None and len(gt_poses) != len(self.entries):
            raise ValueError("gt_poses must have one pose per frame")

    def __len__(self) -> int:
        return len(self.entries)

    @property
    def has_groundtruth(self) -> bool:
        return self.gt_poses is not None and bool(np.isfinite(self.gt_poses).all(axis=(1, 2)).any())

    @property
    def duration(self) -> float:
        return float(self.timestamps[-1] - self.timestamps[0]) if len(self) > 1 else 0.0

    def read_image(self, index: int) -> np.ndarray | None:
        """Decode frame ``index``; on failure record it as skipped (or raise when strict)."""
        entry = self.entries[index]
        image = decode_image(entry.path)
        if image is None:
            missing = not entry.path.exists()
            reason = "missing image file" if missing else "image does not decode"
            cause = "missing image" if missing else "undecodable image"
            self._skip(index, entry.where(), f"{reason}: {entry.path}", cause)
        elif (image.shape[1], image.shape[0]) != (self.camera.width, self.camera.height):
            size = f"{image.shape[1]}x{image.shape[0]}"
            expected = f"{self.camera.width}x{self.camera.height}"
            reason = f"image is {size}, the camera's calibration is for {expected}: {entry.path}"
            self._skip(index, entry.where(), reason, "wrong image size")
            return None
        return image

    def _skip(self, index: int, where: str, reason: str, cause: str) -> None:
        if self.strict:
            raise DatasetError(where, reason)
        log.warning("%s: %s; frame %d skipped", where, reason, index)
        self.skipped.append(SkippedFrame(index, where, reason, cause))

    def __iter__(self) -> Iterator[Frame]:
        return self.frames()

    def frames(self, start: int = 0, previous: tuple[int, float] | None = None) -> Iterator[Frame]:
        """The frames from index ``start`` on, as iterating yields them (readers that override
        ``__iter__``, e.g. video, stream from the start only). ``previous`` is the (index,
        timestamp) of the last frame given out before ``start``: a frame whose timestamp is not
        after it is skipped and counted, as in an uninterrupted stream."""
        for index in range(start, len(self)):
            stamp = self.entries[index].timestamp
            if previous is not None and stamp <= previous[1]:
                cause = "duplicate timestamp" if stamp == previous[1] else "backwards timestamp"
                self._skip(
                    index,
                    self.entries[index].where(),
                    f"{cause} {stamp!r} (frame {previous[0]} has {previous[1]!r})",
                    cause,
                )
                continue
            image = self.read_image(index)
            if image is None:
                continue
            previous = (index, stamp)
            yield self._frame(index, image)

    def _frame(self, index: int, image: np.ndarray) -> Frame:
        entry = self.entries[index]
        pose = None
        if self.gt_poses is not None and np.isfinite(self.gt_poses[index]).all():
            pose = self.gt_poses[index]
        return Frame(index, entry.timestamp, image, str(entry.path), pose)

    def gt_trajectory(self) -> PoseTrajectory3D | None:
        """The ground truth at the frames that have it, as an evo trajectory."""
        if not self.has_groundtruth:
            return None
        assert self.gt_poses is not None
        have = np.isfinite(self.gt_poses).all(axis=(1, 2))
        return PoseTrajectory3D(poses_se3=list(self.gt_poses[have]), timestamps=self.timestamps[have])

    def loop_pairs(self, config: LoopLabelConfig | None = None) -> tuple[np.ndarray | None, str]:
        """GT loop pairs and where they come from: the dataset's own file, else computed from GT poses."""
        if self.gt_loop_pairs is not None:
            return self.gt_loop_pairs, "file"
        if self.has_groundtruth:
            assert self.gt_poses is not None
            return label_loop_pairs(self.gt_poses, self.timestamps, config or LoopLabelConfig()), "gt_poses"
        return None, "none"

    def info(self, config: LoopLabelConfig | None = None) -> dict[str, Any]:
        pairs, source = self.loop_pairs(config)
        return {
            "format": self.format_name,
            "path": str(self.root),
            "frames": len(self),
            "duration": round(self.duration, 6),
            "width": self.camera.width,
            "height": self.camera.height,
            "fx": self.camera.fx,
            "fy": self.camera.fy,
            "cx": self.camera.cx,
            "cy": self.camera.cy,
            "distorted": self.camera.is_distorted,
            "intrinsics_source": self.camera.source,
            "has_groundtruth": self.has_groundtruth,
            "gt_poses": 0
            if self.gt_poses is None
            else int(np.isfinite(self.gt_poses).all(axis=(1, 2)).sum()),
            "gt_loop_pairs": 0 if pairs is None else len(pairs),
            "gt_loop_queries": 0 if pairs is None else len(np.unique(pairs[:, 0])),
            "gt_loop_pairs_source": source,
        }


def every_period(frames: Iterable[Frame], period: float) -> Iterator[Frame]:
    """The frames at least ``period`` seconds after the previously kept one (the first is kept)."""
    last = -np.inf
    for frame in frames:
        if frame.timestamp - last >= period - 1e-9:
            last = frame.timestamp
            yield frame


def first_image_size(entries: Sequence[ImageEntry], tries: int = 5) -> tuple[int, int]:
    """(width, height) of the first decodable image among the first few entries."""
    for entry in entries[:tries]:
        image = decode_image(entry.path)
        if image is not None:
            return image.shape[1], image.shape[0]
    where = entries[0].where() if entries else "dataset"
    raise DatasetError(where, f"none of the first {min(tries, len(entries))} images decodes")


def check_camera_size(camera: CameraIntrinsics, size: tuple[int, int], root: Path) -> CameraIntrinsics:
    """Fail clearly when the calibration was made for another resolution than the images have."""
    if (camera.width, camera.height) != size:
        raise CalibrationError(
            camera.source or root,
            f"calibration is for {camera.width}x{camera.height} images but {root} has {size[0]}x{size[1]}",
        )
    return camera


def list_images(folder: Path) -> list[Path]:
    """Image files of a folder in name order."""
    suffixes = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp"}
    if not folder.is_dir():
        raise DatasetError(folder, "image folder not found")
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in suffixes and p.is_file())


def require_file(path: Path, what: str) -> Path:
    if not path.is_file():
        raise DatasetError(path, f"{what} not found")
    return path


def check_listed_images_exist(entries: Sequence[ImageEntry], strict: bool) -> None:
    """Listed but missing images: an error when strict, else one warning (each is skipped later)."""
    missing = [e for e in entries if not e.path.is_file()]
    if not missing:
        return
    if strict:
        raise DatasetError(missing[0].where(), f"listed image not found: {missing[0].path}")
    log.warning(
        "%d listed images are missing (first: %s, %s); they will be skipped",
        len(missing),
        missing[0].where(),
        missing[0].path,
    )
