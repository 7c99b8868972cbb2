"""Checkpoint and resume of ``symbio run`` (``--checkpoint-every N``, ``--resume DIR``).

Every ``N`` frames the run's whole live state is pickled: the frontend (map, keyframes, velocity,
segments), ``LoopClosing`` with its object detector, loop detector database, verifier and pose-graph
backend, and the ``slam_backend.slam.SlamState`` (results so far, counters, timings), with the random
generators these objects hold (every random draw in the project comes from a seeded numpy Generator or a seed
derived per call, never from a global RNG). Nothing is listed field by field, so new fields of any
component are saved too. What does not pickle, or should not be copied each time:

* ``slam_backend.posegraph.GtsamPoseGraph`` (gtsam objects) pickles as its config and the log of its
  state-changing calls and is rebuilt by replaying them, which reproduces iSAM2 bit for bit;
* frame images (keyframes keep theirs) are stored as their frame index and read from the dataset
  again, for plain image-file readers (``reads_image_files``; others store the pixels);
* ``lcd.vocabulary.Vocabulary`` pickles as its file's path and SHA-256;
* ``lcd.wl._Buffer`` pickles its used part only.

Files in the run's output folder:

* ``checkpoint-FFFFFF.pkl``: the pickled state after frame count FFFFFF;
* ``checkpoint.json``: the header (format, version, frames done, next frame index, the payload's
  file name, size and SHA-256, the run's options, a hash of them, the dataset's fingerprint, and
  ``mac``: an HMAC-SHA256 over the rest of the header and the payload bytes).

A save writes the payload to a temporary file, fsyncs it, renames it into place, then does the same
for the header, and only then deletes the previous payload: the header, replaced last, is the
commit point, so a ``kill -9`` at any moment leaves a header that names a complete payload.
While ``checkpoint.json`` exists the run is unfinished and any output files in the folder are not
final (a checkpointed run deletes stale outputs when it starts or resumes, and its checkpoint once
its outputs are written).

Trust model: a payload is a pickle, and unpickling can run code, so a checkpoint is loaded only if
its HMAC verifies with this user's key (``key_path``: ``$SYMBIO_CHECKPOINT_KEY``, else
``$XDG_CONFIG_HOME/symbiolcd2/checkpoint.key``, default ``~/.config/symbiolcd2/checkpoint.key``; 32
random bytes made on the first save, mode 0600, refused when other users may read or change it).
The key lives outside the run folder, so whoever can write a run folder still cannot forge its
checkpoint; a checkpoint copied to another user or machine resumes only with the key copied too.
The MAC is checked before a byte is unpickled; then ``_StateUnpickler`` admits only the classes a
run's state is made of (``ALLOWED_GLOBALS`` and the classes defined in the project's packages), a
second line of defence. The payload is a plain file of the run folder (no path, no symlink).

Resuming re-opens the dataset with the stored options (the dataset path is stored resolved, so the
working directory does not matter; ``--dataset NEW_PATH`` if it moved), refuses a different dataset
(by content: ``dataset_fingerprint``) or options and a corrupt, truncated, forged or foreign
checkpoint (``CheckpointError`` naming the file), unpickles the state and skips the frames already
processed; the frames that follow see exactly the state the uninterrupted run had, so the final
trajectory is bit-identical.
"""

from __future__ import annotations

import errno
import functools
import hashlib
import hmac
import inspect
import io
import itertools
import json
import logging
import os
import pickle
import re
import secrets
import stat
import time
import weakref
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from frontends.base import Frontend
from frontends.datasets import Dataset
from frontends.datasets.base import SkippedFrame
from frontends.errors import InputFileError, OutputError
from frontends.safe_io import atomic_write_bytes, file_sha256
from frontends.types import Frame
from slam_backend.pipeline import LoopClosing

log = logging.getLogger(__name__)

HEADER_FILE = "checkpoint.json"
FORMAT = "symbio-run-checkpoint"
#: 2: authenticated (``mac``), dataset fingerprint by content. Version 1 is refused: unauthenticated.
VERSION = 2
HEADER_KEYS = ("frames", "next_index", "payload", "bytes", "sha256", "spec", "spec_hash", "dataset", "mac")
#: The only payload names a header may give: a plain file of the run folder.
PAYLOAD_NAME = re.compile(r"checkpoint-\d{6}\.pkl")
KEY_ENV = "SYMBIO_CHECKPOINT_KEY"
KEY_BYTES = 32


class CheckpointError(InputFileError):
    """A checkpoint is missing, corrupt, truncated, forged, foreign, or was made for another dataset
    or config."""


def _short(value: Any, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters: error messages never render huge values."""
    return _clip(repr(value), limit)


def _clip(text: str, limit: int = 80) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


# --- the per-user key that signs checkpoints ------------------------------------------------------


def key_path() -> Path:
    """This user's checkpoint key: ``$SYMBIO_CHECKPOINT_KEY``, else
    ``$XDG_CONFIG_HOME/symbiolcd2/checkpoint.key`` (``~/.config`` without it)."""
    configured = os.environ.get(KEY_ENV)
    if configured:
        return Path(configured).expanduser()
    config_home = os.environ.get("XDG_CONFIG_HOME", "")
    # The XDG base directory spec says a relative value is invalid and is to be ignored.
    base = Path(config_home) if os.path.isabs(config_home) else Path.home() / ".config"
    return base / "symbiolcd2" / "checkpoint.key"


def _check_key_file(path: Path, status: os.stat_result) -> None:
    """CheckpointError unless ``path`` is a regular file of this user that no one else may read or
    change (whoever can read the key can forge checkpoints that run code when resumed)."""
    if not stat.S_ISREG(status.st_mode):
        raise CheckpointError(path, f"the checkpoint key is not a regular file: remove it or set {KEY_ENV}")
    if status.st_uid != os.getuid():
        raise CheckpointError(
            path,
            f"the checkpoint key belongs to uid {status.st_uid}, not to you (uid {os.getuid()}): "
            f"set {KEY_ENV} to a key file of your own (it is created on the next checkpointed run)",
        )
    if status.st_mode & 0o077:
        raise CheckpointError(
            path,
            f"the checkpoint key has permissions {stat.filemode(status.st_mode)}: other users may read "
            f"or change it and forge checkpoints. Run: chmod 600 {path}",
        )


def _read_key(path: Path) -> bytes | None:
    """The key in ``path`` (checked), or None if there is none."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise CheckpointError(path, f"the checkpoint key is unreadable ({exc.strerror or exc})") from None
    try:
        _check_key_file(path, os.fstat(fd))
        key = os.read(fd, 4096)
    finally:
        os.close(fd)
    if len(key) < KEY_BYTES:
        raise CheckpointError(
            path,
            f"the checkpoint key has {len(key)} bytes, fewer than {KEY_BYTES}: remove it (a new one is "
            "made by the next checkpointed run; checkpoints signed with this one cannot be resumed)",
        )
    return key


def _create_key(path: Path) -> bytes:
    """A new random key in ``path``, mode 0600 in a 0700 folder. Written to a temporary name and
    hard-linked into place: no reader sees a partial key, and a concurrent creator's key wins."""
    key = secrets.token_bytes(KEY_BYTES)
    try:
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        temporary = path.with_name(f".{path.name}.{secrets.token_hex(8)}.tmp")
        flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
        fd = os.open(temporary, flags, 0o600)
        try:
            with os.fdopen(fd, "wb") as handle:
                handle.write(key)
                handle.flush()
                os.fsync(handle.fileno())
            created = _link(temporary, path)
        finally:
            temporary.unlink(missing_ok=True)
    except OSError as exc:
        raise CheckpointError(
            path,
            f"cannot create the checkpoint key ({exc.strerror or exc}): set {KEY_ENV} to a writable path",
        ) from None
    if not created:  # another process made it first: use that one
        existing = _read_key(path)
        if existing is None:
            raise CheckpointError(path, "the checkpoint key vanished while it was being created")
        return existing
    log.info("created the checkpoint key %s", path)
    return key


def _link(source: Path, target: Path) -> bool:
    """Hard-link ``source`` as ``target``; False if ``target`` exists (never replaced)."""
    try:
        os.link(source, target)
    except FileExistsError:
        return False
    return True


def signing_key() -> bytes:
    """This user's checkpoint key, created on first use."""
    path = key_path()
    key = _read_key(path)
    return key if key is not None else _create_key(path)


def _mac(key: bytes, header: Mapping[str, Any], payload: bytes) -> str:
    """HMAC-SHA256 over the header's canonical JSON (every field but ``mac``) and the payload."""
    fields = {key_: value for key_, value in header.items() if key_ != "mac"}
    canonical = json.dumps(fields, sort_keys=True, separators=(",", ":")).encode()
    digest = hmac.new(key, digestmod=hashlib.sha256)
    digest.update(len(canonical).to_bytes(8, "big"))  # where the header ends and the payload starts
    digest.update(canonical)
    digest.update(payload)
    return digest.hexdigest()


@dataclass
class RunState:
    """What a checkpoint restores: the live objects of a run and where its frame stream stood."""

    frontend: Frontend
    closing: LoopClosing
    #: ``slam_backend.slam.SlamState`` (typed loosely: the checkpoint stays light to import).
    run: Any
    #: Index of the first frame not processed yet.
    next_index: int
    #: ``Dataset.skipped`` when the checkpoint was made (frames that did not decode).
    skipped: list[SkippedFrame]


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
    """pickle, plus frame images (by index). Nothing of OpenCV is part of the state: the ORB
    extractor (``frontends.orb``) holds only its config."""

    def __init__(self, file: io.BytesIO, images: FrameImages) -> None:
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self.images = images

    def reducer_override(self, obj: Any) -> Any:
        if isinstance(obj, np.ndarray):
            index = self.images.index_of(obj)
            return (_frame_image, (index,)) if index is not None else NotImplemented
        return NotImplemented


#: Top-level packages of the project: a checkpoint may hold any class defined in them.
PROJECT_PACKAGES = frozenset({"frontends", "lcd", "slam_backend", "eval"})
#: The project's functions a checkpoint calls: the reconstructors of what pickles specially.
PROJECT_FUNCTIONS = frozenset(
    {
        (__name__, _frame_image.__name__),
        ("lcd.vocabulary", "_reload"),
        ("slam_backend.posegraph", "_replayed"),
    }
)
#: Every other global a run's state pickles as, recorded from checkpoints of real runs (each loop
#: detector, --no-loops, the replay frontend; synthetic scenes and KITTI), plus a few harmless
#: neighbours (other containers, Windows paths, numpy's reconstructor of non-contiguous arrays).
ALLOWED_GLOBALS: Mapping[str, frozenset[str]] = {
    "builtins": frozenset({"float"}),
    "collections": frozenset({"defaultdict", "OrderedDict", "deque", "Counter"}),
    "pathlib": frozenset({"PosixPath", "PurePosixPath", "WindowsPath", "PureWindowsPath"}),
    # numpy 2 names its core numpy._core, numpy 1 numpy.core.
    "numpy": frozenset({"dtype", "ndarray"}),
    "numpy._core.multiarray": frozenset({"_reconstruct", "scalar"}),
    "numpy.core.multiarray": frozenset({"_reconstruct", "scalar"}),
    "numpy._core.numeric": frozenset({"_frombuffer"}),
    "numpy.core.numeric": frozenset({"_frombuffer"}),
    "networkx.classes.graph": frozenset({"Graph"}),
    "networkx.classes.coreviews": frozenset({"AdjacencyView"}),
    "pycolmap._core": frozenset({"Camera", "CameraModelId"}),
    # symbiolcd's shortlist classifier.
    "sklearn.ensemble._forest": frozenset({"RandomForestClassifier"}),
    "sklearn.tree._classes": frozenset({"DecisionTreeClassifier"}),
    "sklearn.tree._tree": frozenset({"Tree"}),
}
#: The bound methods a run's state holds (pickled as ``getattr(object, name)``): the callbacks
#: ``eval.run.run_odometry`` wires between the frontend and loop closing.
CALLBACKS = frozenset({"apply_correction", "keyframes_in_flux", "movable_boxes"})


def _in_project(module: str) -> bool:
    return module.partition(".")[0] in PROJECT_PACKAGES


class _StateUnpickler(pickle.Unpickler):
    """Unpickles a run's state: frame images are read from the dataset, and only the globals a
    run's state is made of load (a second line of defence behind the checkpoint's MAC)."""

    def __init__(self, file: io.BytesIO, dataset: Dataset, images: FrameImages, path: Path) -> None:
        super().__init__(file)
        self.dataset = dataset
        self.images = images
        self.path = path

    def find_class(self, module: str, name: str) -> Any:
        if module == __name__ and name == _frame_image.__name__:
            return self._frame_image
        if (module, name) == ("builtins", "getattr"):
            return self._callback
        project = _in_project(module)
        # A dotted name would reach through an allowed module into whatever it imported.
        if "." in name or not (project or name in ALLOWED_GLOBALS.get(module, ())):
            raise self._refused(f"{module}.{name}")
        found = super().find_class(module, name)
        # Of the project: classes defined in it only, not its functions nor what a module imported.
        defined_class = inspect.isclass(found) and _in_project(found.__module__)
        if project and (module, name) not in PROJECT_FUNCTIONS and not defined_class:
            raise self._refused(f"{module}.{name}")
        return found

    def _refused(self, what: str) -> CheckpointError:
        return CheckpointError(
            self.path, f"the checkpoint refers to {_clip(what)}, which is not part of a run's state: refused"
        )

    def _callback(self, owner: Any, name: Any) -> Any:
        """``getattr`` as pickle uses it for a bound method, for the run's callbacks only."""
        kind = type(owner)
        if not isinstance(name, str) or name not in CALLBACKS or not _in_project(kind.__module__):
            raise self._refused(f"getattr({kind.__module__}.{kind.__qualname__}, {name!r})")
        method = getattr(owner, name)
        if not inspect.ismethod(method) or method.__self__ is not owner:
            raise self._refused(f"getattr({kind.__module__}.{kind.__qualname__}, {name!r})")
        return method

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
        try:
            return str(value.resolve())
        except (OSError, RuntimeError):  # a symlink loop: the reader names it when it opens the path
            return str(value.absolute())
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
    """What identifies a dataset's data, not where it lies nor how its path was typed: its format,
    frame count and a SHA-256 over the timestamps, the intrinsics and, per frame, the image's path
    relative to the dataset root, its size and the SHA-256 of its bytes (a video's file once).
    Hashing every byte costs about 1 s per GB, once per run and resume (600 640x480 PNGs, 300 MB:
    0.25-0.5 s of a 73 s run; KITTI, 51 frames: 20 ms), so no sampling of the files is needed.
    ``root`` is for information: ``check_dataset`` ignores it."""
    root = Path(os.path.abspath(dataset.root))
    digest = hashlib.sha256()
    digest.update(np.ascontiguousarray(dataset.timestamps, dtype=np.float64).tobytes())
    camera = dataset.camera
    digest.update(np.ascontiguousarray(camera.K, dtype=np.float64).tobytes())
    digest.update(np.ascontiguousarray(camera.dist_coeffs, dtype=np.float64).tobytes())
    digest.update(f"{camera.width}x{camera.height}\n".encode())
    contents: dict[str, str] = {}
    for entry in dataset.entries:
        name = _name_in(root, entry.path)
        if name not in contents:
            contents[name] = _file_digest(entry.path)
        digest.update(f"{name}\0{contents[name]}\n".encode("utf-8", "surrogateescape"))
    return {
        "root": str(root),
        "format": dataset.format_name,
        "frames": len(dataset),
        "sha256": digest.hexdigest(),
    }


def _name_in(root: Path, path: Path) -> str:
    """``path`` relative to ``root`` (posix; "." for a file root such as a video), or its resolved
    absolute path when it lies outside ``root``."""
    absolute = Path(os.path.abspath(path))  # lexical: symlinks inside the dataset stay inside it
    try:
        return absolute.relative_to(root).as_posix()
    except ValueError:
        return absolute.resolve().as_posix()


def _file_digest(path: Path) -> str:
    """``SIZE:SHA256`` of the file, or why there is none (a missing image is part of the data)."""
    try:
        return f"{path.stat().st_size}:{file_sha256(path)}"
    except FileNotFoundError:
        return "missing"
    except OSError as exc:
        return f"unreadable ({errno.errorcode.get(exc.errno or 0, 'error')})"


def discard(out_dir: Path) -> None:
    """Remove the checkpoint of ``out_dir`` (header, payloads, temporary files), if any."""
    for path in [out_dir / HEADER_FILE, *out_dir.glob("checkpoint-*.pkl*"), out_dir / (HEADER_FILE + ".tmp")]:
        path.unlink(missing_ok=True)


class Checkpointer:
    """Saves a run's state into its output folder every ``every`` frames, signed with this user's
    key (read, or created, here: a key problem stops the run before its first frame)."""

    def __init__(
        self,
        out_dir: Path,
        every: int,
        spec: Mapping[str, Any],
        dataset: Dataset,
        register: Callable[[str], Path] | None = None,
    ) -> None:
        self.out_dir = out_dir
        #: Records a file name in the output folder's manifest (``eval.outputs.RunFolder.path``).
        self.register = register or (lambda name: out_dir / name)
        self.every = every
        self.spec = dict(spec)
        self.fingerprint = dataset_fingerprint(dataset)
        self.images = FrameImages()
        self.dataset = dataset
        self.key = signing_key()

    def track(self, frames: Iterable[Frame]) -> Iterable[Frame]:
        """``frames``, with their images remembered when the dataset reads image files."""
        return self.images.track(frames) if reads_image_files(self.dataset) else frames

    def after_frame(self, frame: Frame, frontend: Frontend, closing: LoopClosing, run: Any) -> None:
        """Save when the number of frames processed is a multiple of ``every``."""
        done = len(run.results)
        if done % self.every != 0:
            return
        try:
            # Skips after this frame were met reading ahead; resuming meets them again.
            skipped = [s for s in self.dataset.skipped if s.index <= frame.index]
            self.save(RunState(frontend, closing, run, frame.index + 1, skipped))
        except OutputError as exc:
            # Disk full or a folder turned read-only: the previous checkpoint stays valid (its header
            # is the commit point) and the run goes on; a checkpoint is insurance, not an output.
            run.checkpoint_failures += 1
            log.warning("checkpoint after %d frames not written (%s); the run goes on", done, exc)

    def save(self, state: RunState) -> None:
        """Write ``state`` (the run's ``checkpoints``, ``checkpoint_seconds``, ``checkpoint_bytes``
        count this save; the pickled copy has the figures before it)."""
        start = time.perf_counter()
        frames = len(state.run.results)
        name = f"checkpoint-{frames:06d}.pkl"
        parts = {
            "frontend": state.frontend,
            "closing": state.closing,
            "run": state.run,
            "skipped": state.skipped,
        }
        try:
            payload = dumps_state(parts, self.images)
        except (TypeError, AttributeError, pickle.PicklingError) as exc:  # e.g. an OpenCV object
            raise CheckpointError(
                self.out_dir / name,
                f"this run's state cannot be checkpointed ({_short(exc)}): run without --checkpoint-every",
            ) from None
        atomic_write_bytes(self.register(name), payload)
        header: dict[str, Any] = {
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
        header = json.loads(json.dumps(header))  # the MAC covers the header as resuming reads it
        header["mac"] = _mac(self.key, header, payload)
        atomic_write_bytes(self.register(HEADER_FILE), (json.dumps(header, indent=1) + "\n").encode())
        for old in self.out_dir.glob("checkpoint-*.pkl"):
            if old.name != name:
                old.unlink(missing_ok=True)
        state.run.checkpoints += 1
        state.run.checkpoint_bytes = len(payload)
        state.run.checkpoint_seconds += time.perf_counter() - start


def read_header(out_dir: Path) -> dict[str, Any]:
    """The checkpoint header of ``out_dir``; CheckpointError if it is missing or malformed. It is
    not authenticated yet: ``verified_payload`` does that, before anything in it is used."""
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
    version = header.get("version")
    if version == 1:
        raise CheckpointError(
            path,
            "checkpoint version 1 was made by an older symbiolcd2 that did not sign its checkpoints; "
            "it cannot be resumed safely: start the run again",
        )
    if version != VERSION:
        raise CheckpointError(path, f"checkpoint version {_short(version)}, this build reads {VERSION}")
    missing = set(HEADER_KEYS) - set(header)
    if missing:
        raise CheckpointError(path, f"checkpoint header lacks {', '.join(sorted(missing))}")
    if not isinstance(header["spec"], dict) or not isinstance(header["dataset"], dict):
        raise CheckpointError(path, "corrupt checkpoint header (spec or dataset is not a mapping)")
    if spec_hash(header["spec"]) != header["spec_hash"]:
        raise CheckpointError(path, "checkpoint header is corrupt (its options do not match their hash)")
    return header


def check_dataset(
    header: Mapping[str, Any], dataset: Dataset, out_dir: Path, current: Mapping[str, Any] | None = None
) -> None:
    """CheckpointError unless ``dataset`` holds the data the checkpoint was made on (wherever it
    lies now); ``current``: its fingerprint, if already computed."""
    stored = header["dataset"]
    current = dataset_fingerprint(dataset) if current is None else current
    keys = sorted((set(stored) | set(current)) - {"root"})
    differs = ", ".join(
        f"{key} {_short(stored.get(key))} -> {_short(current.get(key))}"
        for key in keys
        if stored.get(key) != current.get(key)
    )
    if differs:
        raise CheckpointError(
            out_dir / HEADER_FILE,
            f"the checkpoint was made on another dataset or dataset version ({differs}): an image, the "
            "image list, the timestamps or the calibration differ from those of "
            f"{_short(stored.get('root'))}",
        )


def verified_payload(header: Mapping[str, Any], out_dir: Path) -> bytes:
    """The payload the header names, once its name, size, SHA-256 and the MAC over header and
    payload (with this user's key) check: nothing else makes a checkpoint safe to unpickle."""
    header_path = out_dir / HEADER_FILE
    name = header["payload"]
    if not isinstance(name, str) or not PAYLOAD_NAME.fullmatch(name):
        raise CheckpointError(
            header_path, f"payload {_short(name)} is not a checkpoint-NNNNNN.pkl file of the run folder"
        )
    path = out_dir / name
    payload = _read_plain_file(path, header["bytes"])
    if hashlib.sha256(payload).hexdigest() != header["sha256"]:
        raise CheckpointError(path, "checkpoint corrupt: its SHA-256 does not match the header")
    key = _read_key(key_path())
    if key is None:
        raise CheckpointError(
            header_path,
            f"there is no checkpoint key at {key_path()}: this checkpoint was made by another user or "
            "machine (or the key was deleted), and only checkpoints signed with your key are loaded. "
            f"To resume it, copy the key of whoever made it to that path (mode 600) or set {KEY_ENV}",
        )
    mac = header["mac"]
    expected = _mac(key, header, payload).encode()
    if not isinstance(mac, str) or not hmac.compare_digest(mac.encode("utf-8", "replace"), expected):
        raise CheckpointError(
            header_path,
            f"the checkpoint is not signed with your key ({key_path()}): it was changed after it was "
            "written, or made by another user or machine; it is not loaded",
        )
    return payload


def _read_plain_file(path: Path, size: Any) -> bytes:
    """The bytes of ``path``, a regular file (not a symlink) of ``size`` bytes."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise CheckpointError(path, "checkpoint payload is a symbolic link: refused") from None
        raise CheckpointError(path, f"checkpoint payload unreadable ({exc.strerror or exc})") from None
    with os.fdopen(fd, "rb") as handle:
        status = os.fstat(fd)
        if not stat.S_ISREG(status.st_mode):
            raise CheckpointError(path, "checkpoint payload is not a regular file: refused")
        if not isinstance(size, int) or status.st_size > size:
            raise CheckpointError(
                path, f"checkpoint altered: {status.st_size} bytes, the header says {_short(size)}"
            )
        if status.st_size < size:
            raise CheckpointError(path, f"checkpoint truncated: {status.st_size} of {size} bytes")
        return handle.read(size)


def load_state(header: Mapping[str, Any], out_dir: Path, dataset: Dataset, images: FrameImages) -> RunState:
    """Unpickle the payload the header names (verified first: ``verified_payload``); frame images
    are read from ``dataset`` and remembered in ``images`` (those of the resumed run's checkpointer)."""
    payload = verified_payload(header, out_dir)
    path = out_dir / str(header["payload"])
    try:
        state = _StateUnpickler(io.BytesIO(payload), dataset, images, path).load()
    except CheckpointError:
        raise
    except Exception as exc:  # any unpickling failure means the file cannot be resumed from
        raise CheckpointError(path, f"checkpoint does not load ({_short(exc)})") from None
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
