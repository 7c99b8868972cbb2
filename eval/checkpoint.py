"""Checkpoint and resume of ``symbio run`` (``--checkpoint-every N``, ``--resume DIR``).

Every ``N`` frames the run's whole live state is pickled: the frontend (map, keyframes, velocity,
segments), ``LoopClosing`` with its object detector, loop detector database, verifier and pose-graph
backend, and the ``PipelineRun`` (results so far, counters, timings), with the random generators
these objects hold (every random draw in the project comes from a seeded numpy Generator or a seed
derived per call, never from a global RNG). Nothing is listed field by field, so new fields of any
component are saved too. What does not pickle, or should not be copied each time:

* ``cv2.ORB`` (no pickle support in OpenCV) is rebuilt from its own parameters by
  ``_StatePickler.reducer_override``;
* ``slam_backend.posegraph.GtsamPoseGraph`` (gtsam objects) pickles as its config and the log of its
  state-changing calls and is rebuilt by replaying them, which reproduces iSAM2 bit for bit;
* frame images (keyframes keep theirs) are stored as their frame index and read from the dataset
  again, for plain image-file readers (``reads_image_files``; others store the pixels);
* ``lcd.vocabulary.Vocabulary`` pickles as its file's path and SHA-256;
* ``lcd.wl._Buffer`` pickles its used part only.

Files in the run's output folder:

* ``checkpoint-FFFFFF.pkl``: the pickled state after frame count FFFFFF;
* ``checkpoint.json``: the header (format, version, frames done, next frame index, the payload's
  file name, size and SHA-256, the run's options, a hash of them, the dataset's fingerprint).

A save writes the payload to a temporary file, fsyncs it, renames it into place, then does the same
for the header, and only then deletes the previous payload: the header, replaced last, is the
commit point, so a ``kill -9`` at any moment leaves a header that names a complete payload.
While ``checkpoint.json`` exists the run is unfinished and any output files in the folder are not
final (a checkpointed run deletes stale outputs when it starts or resumes, and its checkpoint once
its outputs are written).

Resuming re-opens the dataset with the stored options, refuses a different dataset or options and a
corrupt or truncated checkpoint (``CheckpointError`` naming the file), unpickles the state and skips
the frames already processed; the frames that follow see exactly the state the uninterrupted run
had, so the final trajectory is bit-identical. A checkpoint is a pickle: loading one runs code, so
resume only checkpoints of your own runs, made by the same code version.
"""

from __future__ import annotations

import functools
import hashlib
import io
import itertools
import json
import logging
import os
import pickle
import time
import weakref
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from frontends.base import Frontend
from frontends.datasets import Dataset
from frontends.datasets.base import SkippedFrame
from frontends.errors import InputFileError
from frontends.types import Frame
from slam_backend.pipeline import LoopClosing

log = logging.getLogger(__name__)

HEADER_FILE = "checkpoint.json"
FORMAT = "symbio-run-checkpoint"
VERSION = 1
HEADER_KEYS = ("frames", "next_index", "payload", "bytes", "sha256", "spec", "spec_hash", "dataset")


class CheckpointError(InputFileError):
    """A checkpoint is missing, corrupt, truncated, or was made for another dataset or config."""


@dataclass
class RunState:
    """What a checkpoint restores: the live objects of a run and where its frame stream stood."""

    frontend: Frontend
    closing: LoopClosing
    #: ``eval.run.PipelineRun`` (typed loosely: eval.run imports this module).
    run: Any
    #: Index of the first frame not processed yet.
    next_index: int
    #: ``Dataset.skipped`` when the checkpoint was made (frames that did not decode).
    skipped: list[SkippedFrame]


def _orb_parameters(orb: Any) -> dict[str, Any]:
    return {
        "nfeatures": orb.getMaxFeatures(),
        "scaleFactor": orb.getScaleFactor(),
        "nlevels": orb.getNLevels(),
        "edgeThreshold": orb.getEdgeThreshold(),
        "firstLevel": orb.getFirstLevel(),
        "WTA_K": orb.getWTA_K(),
        "scoreType": orb.getScoreType(),
        "patchSize": orb.getPatchSize(),
        "fastThreshold": orb.getFastThreshold(),
    }


def _new_orb(parameters: dict[str, Any]) -> Any:
    return cv2.ORB.create(**parameters)


class FrameImages:
    """The images of the frames a run has read, by identity: a checkpoint stores a frame's index
    instead of its pixels (keyframes keep their images; at 640x480 that is 0.9 MB per keyframe),
    and resuming reads them from the dataset again (checked by its fingerprint)."""

    def __init__(self) -> None:
        self._index: dict[int, tuple[weakref.ref[np.ndarray], int]] = {}

    def remember(self, image: np.ndarray, index: int) -> None:
        key = id(image)
        self._index[key] = (weakref.ref(image, functools.partial(self._forget, key)), index)

    def _forget(self, key: int, reference: weakref.ref[np.ndarray]) -> None:
        entry = self._index.get(key)
        if entry is not None and entry[0] is reference:
            del self._index[key]

    def index_of(self, array: np.ndarray) -> int | None:
        entry = self._index.get(id(array))
        return entry[1] if entry is not None and entry[0]() is array else None

    def track(self, frames: Iterable[Frame]) -> Iterator[Frame]:
        for frame in frames:
            self.remember(frame.image, frame.index)
            yield frame


def reads_image_files(dataset: Dataset) -> bool:
    """Whether ``dataset`` is a plain reader of image files: frame i is ``read_image(i)`` exactly,
    so a checkpoint may refer to frame images and resuming may start at a frame index. Video
    (seeking is not exact for every codec) and readers or wrappers that override iteration or
    reading (they may change the images) are not: their images are stored and the frames before
    the resume point are read and dropped."""
    kind = type(dataset)
    return (
        isinstance(dataset, Dataset)
        and kind.__iter__ is Dataset.__iter__
        and kind.frames is Dataset.frames
        and kind.read_image is Dataset.read_image
    )


def _frame_image(index: int) -> np.ndarray:
    """Stands for frame ``index``'s image in a checkpoint; ``_StateUnpickler`` resolves it."""
    raise pickle.UnpicklingError(f"frame {index}'s image: load checkpoints with eval.checkpoint.load_state")


class _StatePickler(pickle.Pickler):
    """pickle, plus OpenCV's ORB (rebuilt from its parameters) and frame images (by index)."""

    def __init__(self, file: io.BytesIO, images: FrameImages) -> None:
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self.images = images

    def reducer_override(self, obj: Any) -> Any:
        if isinstance(obj, np.ndarray):
            index = self.images.index_of(obj)
            return (_frame_image, (index,)) if index is not None else NotImplemented
        if isinstance(obj, cv2.ORB):
            return _new_orb, (_orb_parameters(obj),)
        return NotImplemented


class _StateUnpickler(pickle.Unpickler):
    def __init__(self, file: io.BytesIO, dataset: Dataset, images: FrameImages, path: Path) -> None:
        super().__init__(file)
        self.dataset = dataset
        self.images = images
        self.path = path

    def find_class(self, module: str, name: str) -> Any:
        if module == __name__ and name == _frame_image.__name__:
            return self._frame_image
        return super().find_class(module, name)

    def _frame_image(self, index: int) -> np.ndarray:
        image = self.dataset.read_image(index)
        if image is None:
            raise CheckpointError(self.path, f"frame {index}'s image no longer reads from the dataset")
        self.images.remember(image, index)
        return image


def dumps_state(state: Any, images: FrameImages) -> bytes:
    buffer = io.BytesIO()
    _StatePickler(buffer, images).dump(state)
    return buffer.getvalue()


def _json_value(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value.resolve())
    if isinstance(value, (list, tuple)):
        return [_json_value(v) for v in value]
    return value


def run_spec(options: Mapping[str, Any], ignored: Iterable[str]) -> dict[str, Any]:
    """The options that define a run (JSON values, paths resolved), without the ``ignored`` ones."""
    skip = set(ignored)
    return {key: _json_value(value) for key, value in sorted(options.items()) if key not in skip}


def spec_hash(spec: Mapping[str, Any]) -> str:
    return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()


def dataset_fingerprint(dataset: Dataset) -> dict[str, Any]:
    """Root, format, frame count and a hash of the image list, timestamps and intrinsics."""
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(dataset.timestamps).tobytes())
    for entry in dataset.entries:
        digest.update(str(entry.path).encode() + b"\0")
    camera = dataset.camera
    digest.update(np.ascontiguousarray(camera.K, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(camera.dist_coeffs, dtype=np.float64).tobytes())
    digest.update(f"{camera.width}x{camera.height}".encode())
    return {
        "root": str(Path(dataset.root).resolve()),
        "format": dataset.format_name,
        "frames": len(dataset),
        "sha256": digest.hexdigest(),
    }


def _fsync_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically: temporary file, fsync, rename, fsync of the folder."""
    temporary = path.with_name(path.name + ".tmp")
    with temporary.open("wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)
    folder = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(folder)
    finally:
        os.close(folder)


def discard(out_dir: Path) -> None:
    """Remove the checkpoint of ``out_dir`` (header, payloads, temporary files), if any."""
    for path in [out_dir / HEADER_FILE, *out_dir.glob("checkpoint-*.pkl*"), out_dir / (HEADER_FILE + ".tmp")]:
        path.unlink(missing_ok=True)


class Checkpointer:
    """Saves a run's state into its output folder every ``every`` frames."""

    def __init__(self, out_dir: Path, every: int, spec: Mapping[str, Any], dataset: Dataset) -> None:
        self.out_dir = out_dir
        self.every = every
        self.spec = dict(spec)
        self.fingerprint = dataset_fingerprint(dataset)
        self.images = FrameImages()
        self.dataset = dataset

    def track(self, frames: Iterable[Frame]) -> Iterable[Frame]:
        """``frames``, with their images remembered when the dataset reads image files."""
        return self.images.track(frames) if reads_image_files(self.dataset) else frames

    def after_frame(self, frame: Frame, frontend: Frontend, closing: LoopClosing, run: Any) -> None:
        """Save when the number of frames processed is a multiple of ``every``."""
        done = len(run.results)
        if done % self.every == 0:
            self.save(RunState(frontend, closing, run, frame.index + 1, list(self.dataset.skipped)))

    def save(self, state: RunState) -> None:
        """Write ``state`` (the run's ``checkpoints``, ``checkpoint_seconds``, ``checkpoint_bytes``
        count this save; the pickled copy has the figures before it)."""
        start = time.perf_counter()
        payload = dumps_state(
            {
                "frontend": state.frontend,
                "closing": state.closing,
                "run": state.run,
                "skipped": state.skipped,
            },
            self.images,
        )
        frames = len(state.run.results)
        name = f"checkpoint-{frames:06d}.pkl"
        self.out_dir.mkdir(parents=True, exist_ok=True)
        _fsync_write(self.out_dir / name, payload)
        header = {
            "format": FORMAT,
            "version": VERSION,
            "frames": frames,
            "next_index": state.next_index,
            "payload": name,
            "bytes": len(payload),
            "sha256": hashlib.sha256(payload).hexdigest(),
            "spec": self.spec,
            "spec_hash": spec_hash(self.spec),
            "dataset": self.fingerprint,
        }
        _fsync_write(self.out_dir / HEADER_FILE, (json.dumps(header, indent=1) + "\n").encode())
        for old in self.out_dir.glob("checkpoint-*.pkl"):
            if old.name != name:
                old.unlink(missing_ok=True)
        state.run.checkpoints += 1
        state.run.checkpoint_bytes = len(payload)
        state.run.checkpoint_seconds += time.perf_counter() - start


def read_header(out_dir: Path) -> dict[str, Any]:
    """The checkpoint header of ``out_dir``; CheckpointError if it is missing or malformed."""
    path = out_dir / HEADER_FILE
    try:
        header = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CheckpointError(
            path,
            "no checkpoint: the run was started without --checkpoint-every, or it finished (its "
            "checkpoint is deleted once its outputs are written)",
        ) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CheckpointError(path, f"corrupt checkpoint header ({exc})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise CheckpointError(path, f"not a checkpoint header (format is not {FORMAT!r})")
    if header.get("version") != VERSION:
        raise CheckpointError(
            path, f"checkpoint version {header.get('version')!r}, this build reads {VERSION}"
        )
    missing = set(HEADER_KEYS) - set(header)
    if missing:
        raise CheckpointError(path, f"checkpoint header lacks {', '.join(sorted(missing))}")
    if spec_hash(header["spec"]) != header["spec_hash"]:
        raise CheckpointError(path, "checkpoint header is corrupt (its options do not match their hash)")
    return header


def check_dataset(header: Mapping[str, Any], dataset: Dataset, out_dir: Path) -> None:
    """CheckpointError unless ``dataset`` is the one the checkpoint was made on."""
    stored, current = header["dataset"], dataset_fingerprint(dataset)
    if stored != current:
        differs = ", ".join(
            f"{key} {stored.get(key)!r} -> {current.get(key)!r}"
            for key in sorted(set(stored) | set(current))
            if stored.get(key) != current.get(key)
        )
        raise CheckpointError(
            out_dir / HEADER_FILE,
            f"the checkpoint was made on another dataset or dataset version ({differs})",
        )


def load_state(header: Mapping[str, Any], out_dir: Path, dataset: Dataset, images: FrameImages) -> RunState:
    """Unpickle the payload the header names (size and SHA-256 checked first); frame images are
    read from ``dataset`` and remembered in ``images`` (those of the resumed run's checkpointer)."""
    path = out_dir / str(header["payload"])
    try:
        payload = path.read_bytes()
    except OSError as exc:
        raise CheckpointError(path, f"checkpoint payload unreadable ({exc.strerror or exc})") from None
    if len(payload) != header["bytes"]:
        raise CheckpointError(path, f"checkpoint truncated: {len(payload)} of {header['bytes']} bytes")
    if hashlib.sha256(payload).hexdigest() != header["sha256"]:
        raise CheckpointError(path, "checkpoint corrupt: its SHA-256 does not match the header")
    try:
        state = _StateUnpickler(io.BytesIO(payload), dataset, images, path).load()
    except CheckpointError:
        raise
    except Exception as exc:  # any unpickling failure means the file cannot be resumed from
        raise CheckpointError(path, f"checkpoint does not load ({exc!r})") from None
    return RunState(
        state["frontend"], state["closing"], state["run"], int(header["next_index"]), state["skipped"]
    )


def remaining(dataset: Dataset, max_frames: int | None, resume: RunState) -> Iterable[Frame]:
    """The frames of ``islice(dataset, max_frames)`` that the checkpointed run had not processed:
    read from the resume point on (with the frames skipped before it restored to
    ``dataset.skipped``) when the dataset reads image files, else read from the start and dropped."""
    if reads_image_files(dataset):
        dataset.skipped = list(resume.skipped)
        left = None if max_frames is None else max(max_frames - len(resume.run.results), 0)
        results = resume.run.results
        previous = (results[-1].frame_index, results[-1].timestamp) if results else None
        return itertools.islice(dataset.frames(resume.next_index, previous), left)
    frames = itertools.islice(dataset, max_frames)
    return (frame for frame in frames if frame.index >= resume.next_index)
