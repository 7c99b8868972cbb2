"""The dataset model every reader produces: a streamed image sequence with its camera.

Images are decoded one at a time while iterating, never all held in memory. An image that is
missing, fails to decode or has another size than the camera's is skipped with a warning and
recorded in ``Dataset.skipped`` (with the
index file and line that listed it); ``strict=True`` turns that into a ``DatasetError``.

Image files are untrusted: each is read as bytes (any file name works, including names that are
not UTF-8) and its header (width, height; read by Pillow) is checked against the calibration
before OpenCV decodes it, so a huge image of a few hundred kilobytes is skipped as "wrong image
size" without being decoded. A file larger than its header's image could need (8 bytes a pixel
plus ``IMAGE_METADATA_BYTES``), or in a format whose header is not read (``HEADER_FORMATS``), does
not decode. Where no calibration gives the size yet (``first_image_size``) images above
``MAX_IMAGE_PIXELS`` are refused.

The built-in readers reject index files whose timestamps do not increase when opening them; a
frame whose timestamp is not after the previous frame's (a reader that does not check, e.g. a
plugin) is skipped and recorded the same way, so a frontend never sees time run backwards.
"""

from __future__ import annotations

import functools
import logging
import queue
import threading
import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, ClassVar

import cv2
import numpy as np
from evo.core.trajectory import PoseTrajectory3D
from PIL import Image

from frontends.errors import CalibrationError, DatasetError, display_path
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
            return display_path(self.path)
        listed_in = display_path(self.listed_in)
        return f"{listed_in}:{self.line}" if self.line is not None else listed_in


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


#: Largest image decoded when no calibration gives the size to expect: 100 megapixels, above any
#: camera a monocular SLAM run uses; decoding more takes gigabytes for a file of a few hundred KB.
MAX_IMAGE_PIXELS = 100_000_000
#: Bytes an image file may hold beyond 8 a pixel (16-bit RGBA stored uncompressed, the most any
#: encoding of the image needs): room for metadata such as EXIF, ICC profiles and thumbnails.
IMAGE_METADATA_BYTES = 16 << 20
#: Pillow formats whose header is read before decoding: those OpenCV decodes to 8 or 16 bits.
#: A file in another format (PAM, PFM, HDR, EXR) is skipped as undecodable.
HEADER_FORMATS = ("PNG", "JPEG", "BMP", "TIFF", "PPM", "WEBP", "JPEG2000", "GIF", "SUN", "AVIF")


class ImageSkipped(Exception):
    """Why an image file is not used: ``cause`` (one of ``SKIP_CAUSES``) and a reason naming it."""

    def __init__(self, cause: str, reason: str) -> None:
        super().__init__(reason)
        self.cause = cause
        self.reason = reason


@functools.cache
def _header_formats() -> tuple[str, ...]:
    Image.init()  # a format Pillow was built without (e.g. AVIF) is left out, not a KeyError
    return tuple(name for name in HEADER_FORMATS if name in Image.OPEN)


def _header_size(handle: IO[bytes], shown: str) -> tuple[int, int] | None:
    """(width, height) from the header of the image file open in ``handle``, without decoding it;
    None when the header declares more pixels than Pillow tells the size of (its decompression-bomb
    limit, 179 megapixels by default)."""
    try:
        with warnings.catch_warnings():
            # Sizes are checked here, and a damaged file is reported as skipped, not as a warning.
            warnings.simplefilter("ignore")
            with Image.open(handle, formats=_header_formats()) as header:
                width, height = header.size
    except Image.DecompressionBombError:
        return None
    except Exception as exc:  # any failure of a parser fed untrusted bytes means: does not decode
        if isinstance(exc, Image.UnidentifiedImageError):
            detail = "not an image format the readers decode"
        else:  # Pillow's messages may quote the file name: printable, and short
            detail = display_path(f"{type(exc).__name__}: {exc}")[:120]
        raise ImageSkipped("undecodable image", f"image does not decode ({detail}): {shown}") from None
    return int(width), int(height)


def load_image(path: Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """The image file at ``path`` as 8-bit grey or BGR, its header checked before it is decoded
    against ``size`` (width, height) or, without ``size``, against ``MAX_IMAGE_PIXELS``.

    Raises ``ImageSkipped`` when the file is missing, does not decode or has another size."""
    shown = display_path(path)
    try:
        # Bytes I/O, not cv2.imread: it crashes on a file name that is not UTF-8.
        handle = open(path, "rb")  # noqa: SIM115 (closed by the with block below)
    except (FileNotFoundError, ValueError):  # ValueError: a NUL byte, which no file name holds
        raise ImageSkipped("missing image", f"missing image file: {shown}") from None
    except OSError as exc:
        raise ImageSkipped("undecodable image", f"image does not decode ({exc.strerror}): {shown}") from None
    with handle:
        declared = _header_size(handle, shown)
        if declared is None:
            found = f"larger than {2 * (Image.MAX_IMAGE_PIXELS or 0) / 1e6:.0f} megapixels"
        elif size is not None:
            found = f"{declared[0]}x{declared[1]}"
        else:
            found = f"{declared[0]}x{declared[1]} ({declared[0] * declared[1] / 1e6:.0f} megapixels)"
        if size is not None and declared != size:
            expected = f"{size[0]}x{size[1]}"
            reason = f"image is {found}, the camera's calibration is for {expected}: {shown}"
            raise ImageSkipped("wrong image size", reason)
        if declared is None or (size is None and declared[0] * declared[1] > MAX_IMAGE_PIXELS):
            cap = f"{MAX_IMAGE_PIXELS / 1e6:.0f} megapixels"
            reason = f"image is {found}, more than the {cap} an image may have without a calibration: {shown}"
            raise ImageSkipped("wrong image size", reason)
        width, height = declared
        limit = 8 * width * height + IMAGE_METADATA_BYTES
        handle.seek(0)
        data = handle.read(limit + 1)
    if len(data) > limit:
        reason = f"the file has more than the {limit} bytes a {width}x{height} image needs"
        raise ImageSkipped("undecodable image", f"image does not decode ({reason}): {shown}")
    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        image = None
    image = _eight_bit(image)
    if image is None:
        raise ImageSkipped("undecodable image", f"image does not decode: {shown}")
    if size is not None and (image.shape[1], image.shape[0]) != size:  # a header that lied
        found = f"{image.shape[1]}x{image.shape[0]}"
        reason = f"image is {found}, the camera's calibration is for {size[0]}x{size[1]}: {shown}"
        raise ImageSkipped("wrong image size", reason)
    return image


def _eight_bit(image: np.ndarray | None) -> np.ndarray | None:
    """A decoded image as 8-bit grey or BGR; None for an empty or non-integer one."""
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


def decode_image(path: Path) -> np.ndarray | None:
    """Read an image as 8-bit grey or BGR; None when it is missing, does not decode or is larger
    than ``MAX_IMAGE_PIXELS`` (``load_image`` says why)."""
    try:
        return load_image(path)
    except ImageSkipped as skipped:
        log.debug("%s", skipped.reason)
        return None


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
        try:
            return load_image(entry.path, (self.camera.width, self.camera.height))
        except ImageSkipped as skipped:
            self._skip(index, entry.where(), skipped.reason, skipped.cause)
            return None

    def forget_skips_after(self, index: int) -> None:
        """Drop the records of frames after ``index`` (read ahead, never reached by the run)."""
        self.skipped[:] = [s for s in self.skipped if s.index <= index]  # in place: wrappers share it

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
            "path": display_path(self.root),
            "frames": len(self),
            "duration": round(self.duration, 6),
            "width": self.camera.width,
            "height": self.camera.height,
            "fx": self.camera.fx,
            "fy": self.camera.fy,
            "cx": self.camera.cx,
            "cy": self.camera.cy,
            "distorted": self.camera.is_distorted,
            "intrinsics_source": display_path(self.camera.source),
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
    """(width, height) of the first decodable image among the first few entries; an image above
    ``MAX_IMAGE_PIXELS`` is an error (not decoded): it would set the size every frame must have."""
    reasons = []
    for entry in entries[:tries]:
        try:
            image = load_image(entry.path)
        except ImageSkipped as skipped:
            if skipped.cause == "wrong image size":  # without an expected size: too large
                raise DatasetError(entry.where(), skipped.reason) from None
            reasons.append(skipped.reason)
            continue
        return image.shape[1], image.shape[0]
    where = entries[0].where() if entries else "dataset"
    first = f" (first: {reasons[0]})" if reasons else ""
    raise DatasetError(where, f"none of the first {min(tries, len(entries))} images decodes{first}")


def check_camera_size(camera: CameraIntrinsics, size: tuple[int, int], root: Path) -> CameraIntrinsics:
    """Fail clearly when the calibration was made for another resolution than the images have."""
    if (camera.width, camera.height) != size:
        raise CalibrationError(
            camera.source or display_path(root),
            f"calibration is for {camera.width}x{camera.height} images but {display_path(root)} has "
            f"{size[0]}x{size[1]}",
        )
    return camera


def list_images(folder: Path) -> list[Path]:
    """Image files of a folder in name order."""
    suffixes = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp"}
    if not folder.is_dir():
        raise DatasetError(display_path(folder), "image folder not found")
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in suffixes and p.is_file())


def require_file(path: Path, what: str) -> Path:
    if not path.is_file():
        raise DatasetError(display_path(path), f"{what} not found")
    return path


def check_listed_images_exist(entries: Sequence[ImageEntry], strict: bool) -> None:
    """Listed but missing images: an error when strict, else one warning (each is skipped later)."""
    missing = [e for e in entries if not e.path.is_file()]
    if not missing:
        return
    if strict:
        raise DatasetError(missing[0].where(), f"listed image not found: {display_path(missing[0].path)}")
    log.warning(
        "%d listed images are missing (first: %s, %s); they will be skipped",
        len(missing),
        missing[0].where(),
        display_path(missing[0].path),
    )


class ReadAhead(Iterator[Frame]):
    """``frames`` read by a background thread up to ``depth`` frames ahead of the consumer.

    Decoding a 640x480 PNG takes ~10 ms; OpenCV releases the GIL while it decodes, so on two cores
    the next frame decodes while this one is tracked. Frames come out in order, and an exception
    of the reader comes out where it happened in the sequence. ``close()`` stops the reader;
    frames it read ahead are dropped, and ``last_index`` (the index of the last frame handed out,
    -1 before the first) tells what the consumer reached, so a dataset's ``skipped`` can be cut
    back to it (``Dataset.forget_skips_after``)."""

    _END = object()

    def __init__(self, frames: Iterable[Frame], depth: int = 2) -> None:
        if depth < 1:
            raise ValueError("read-ahead depth must be >= 1")
        self._source = iter(frames)
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._done = False
        #: Index of the last frame handed out (-1 before the first).
        self.last_index = -1
        #: The source ended or raised, and that was handed out.
        self.finished = False
        self._thread = threading.Thread(target=self._read, name="symbio-read-ahead", daemon=True)
        self._thread.start()

    def _put(self, item: Any) -> bool:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _read(self) -> None:
        try:
            for frame in self._source:
                if not self._put(frame):
                    return
        except BaseException as exc:  # handed to the consumer at this point of the sequence
            self._put(exc)
            return
        self._put(self._END)

    def __iter__(self) -> ReadAhead:
        return self

    def __next__(self) -> Frame:
        if self._done:
            raise StopIteration
        item = self._queue.get()
        if item is self._END:
            self._done = self.finished = True
            self._thread.join()
            raise StopIteration
        if isinstance(item, BaseException):
            self._done = self.finished = True
            self._thread.join()
            raise item
        self.last_index = item.index
        return item

    def close(self) -> None:
        """Stop the reader thread and wait for it (a frame being decoded finishes first)."""
        self._done = True
        self._stop.set()
        self._thread.join()
