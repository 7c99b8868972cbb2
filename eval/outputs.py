"""The output folder of a command (``symbio run --out DIR``, ``symbio demo --out DIR``).

A command claims its folder before it computes anything:

* a path that is a file, or a folder it cannot write, is refused at once (``OutputError``);
* a lock (``fcntl.flock`` on ``.symbio.lock``, released by the kernel when the process dies, even
  on ``kill -9``) stops a second command from writing into the same folder;
* the folder's manifest (``.symbio-outputs.json``) lists every file the command writes there. A
  non-empty folder holding files that no manifest lists (the user's files, or an earlier
  version's outputs) is refused unless ``overwrite`` is given; even then only the names this
  command writes are replaced, and nothing else in the folder is touched;
* the files of the earlier run that the manifest lists are removed when the new run starts (a
  resumed run keeps its checkpoint), so the folder never mixes two runs.

Files are written through ``frontends.safe_io`` (temporary name, fsync, rename): a symlink at an
output name is replaced, never followed, and a reader never sees half a file. Only plain names
inside the folder are written; sub-folders the command makes are registered too, and a symlinked
sub-folder is refused.
"""

from __future__ import annotations

import contextlib
import errno
import fnmatch
import json
import logging
import os
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import TracebackType
from typing import IO, Any

from frontends.errors import OutputError
from frontends.safe_io import (
    TEMP_PREFIX,
    atomic_path,
    atomic_write_bytes,
    atomic_write_text,
    describe_os_error,
)

try:  # POSIX; elsewhere a second run into one folder is not detected
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

MANIFEST_FILE = ".symbio-outputs.json"
LOCK_FILE = ".symbio.lock"
MANIFEST_FORMAT = "symbio-outputs"
#: The most names an error message lists.
SHOWN = 5


def _plain_name(name: str) -> str:
    if not name or name in (".", "..") or "/" in name or os.sep in name or "\0" in name:
        raise ValueError(f"not a plain file name: {name!r}")
    return name


class RunFolder:
    """An output folder claimed by one command; use as a context manager (``with RunFolder(...)``).

    ``names``: the file names the command writes (what ``overwrite`` may replace). ``resume``: keep
    the earlier run's files matching the globs ``keep`` (the checkpoint being resumed).
    """

    def __init__(
        self,
        path: str | Path,
        command: str,
        *,
        names: Iterable[str] = (),
        keep: Iterable[str] = (),
        overwrite: bool = False,
        resume: bool = False,
    ) -> None:
        self.root = Path(path)
        self.command = command
        self.names = {_plain_name(n) for n in names}
        self.keep = list(keep)
        self.overwrite = overwrite
        self.resume = resume
        self.files: set[str] = set()
        self.folders: set[str] = set()
        self._lock: IO[bytes] | None = None

    # -- claiming ---------------------------------------------------------------------------
    def __enter__(self) -> RunFolder:
        self.claim()
        return self

    def __exit__(
        self, kind: type[BaseException] | None, value: BaseException | None, trace: TracebackType | None
    ) -> None:
        self.release()

    def claim(self) -> None:
        """Create, lock and clean the folder (see the module docstring); OutputError if it cannot."""
        if self.root.exists() and not self.root.is_dir():
            raise OutputError(self.root, "is not a folder; choose a folder for --out")
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(
                self.root, f"cannot create the output folder ({describe_os_error(exc)})"
            ) from None
        self._acquire_lock()
        try:
            self._check_and_clean()
        except BaseException:
            self.release()
            raise

    def _acquire_lock(self) -> None:
        path = self.root / LOCK_FILE
        try:
            descriptor = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o644)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise OutputError(path, "is a symbolic link; remove it") from None
            raise OutputError(self.root, f"cannot write here ({describe_os_error(exc)})") from None
        handle = os.fdopen(descriptor, "rb+")
        if fcntl is not None:
            try:
                fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = handle.read(32).decode("ascii", "replace").strip() or "unknown"
                handle.close()
                raise OutputError(
                    self.root,
                    f"another symbio command (pid {holder}) is writing into this folder; wait for it "
                    "to finish or choose another --out",
                ) from None
        handle.seek(0)
        handle.truncate()
        handle.write(f"{os.getpid()}\n".encode())
        handle.flush()
        self._lock = handle

    def release(self) -> None:
        """Unlock the folder (the lock file stays; it is empty of meaning without the lock)."""
        if self._lock is not None:
            self._lock.close()  # closing the descriptor drops the flock
            self._lock = None

    def _earlier(self) -> tuple[set[str], set[str]]:
        """Files and folders the folder's manifest lists (empty without a valid one)."""
        path = self.root / MANIFEST_FILE
        if path.is_symlink() or not path.is_file():
            return set(), set()
        try:
            manifest = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, ValueError):
            return set(), set()
        if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
            return set(), set()

        def strings(key: str) -> list[str]:
            values = manifest.get(key, [])
            return [v for v in values if isinstance(v, str)] if isinstance(values, list) else []

        return set(strings("files")), set(strings("folders"))

    def _check_and_clean(self) -> None:
        files, folders = self._earlier()

        def ours(name: str, globs: Iterable[str]) -> bool:
            return any(fnmatch.fnmatchcase(name, p) for p in globs)

        present = [
            n for n in sorted(os.listdir(self.root)) if n not in (LOCK_FILE, MANIFEST_FILE)
        ]  # fmt: skip
        temporary = {n for n in present if n.startswith(TEMP_PREFIX)}
        earlier = {n for n in present if n in files or n in folders}
        foreign = [n for n in present if n not in earlier and n not in temporary]
        if foreign and not self.overwrite:
            shown = ", ".join(repr(n) for n in foreign[:SHOWN]) + (" ..." if len(foreign) > SHOWN else "")
            raise OutputError(
                self.root,
                f"the folder holds {len(foreign)} entries that symbio did not write ({shown}); choose an "
                f"empty or new --out folder, or pass --overwrite (it replaces only the files "
                f"'{self.command}' writes and leaves the others alone)",
            )
        stale = temporary | earlier
        if self.overwrite:
            stale |= self.names & set(present)
        if self.resume:  # the checkpoint being resumed stays
            stale = {n for n in stale if not ours(n, self.keep)}
        for name in sorted(stale):
            path = self.root / name
            if path.is_dir() and not path.is_symlink():
                continue  # never delete a folder tree; the command reuses or refuses it
            try:
                path.unlink(missing_ok=True)
            except OSError as exc:
                raise OutputError(
                    path, f"cannot remove the earlier run's file ({describe_os_error(exc)})"
                ) from None
        if stale - temporary:
            log.info("%s: removed %d files of an earlier run", self.root, len(stale - temporary))
        self.folders = {f for f in folders if (self.root / f).is_dir() and not (self.root / f).is_symlink()}
        self.files = {n for n in earlier - stale if not (self.root / n).is_dir()}
        self._write_manifest()

    # -- writing ----------------------------------------------------------------------------
    def _write_manifest(self) -> None:
        manifest = {
            "format": MANIFEST_FORMAT,
            "command": self.command,
            "pid": os.getpid(),
            "updated": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "files": sorted(self.files),
            "folders": sorted(self.folders),
        }
        atomic_write_text(self.root / MANIFEST_FILE, json.dumps(manifest, indent=1) + "\n", fsync=False)

    def path(self, name: str) -> Path:
        """The path of output ``name`` (a plain name), recorded in the manifest before it exists."""
        _plain_name(name)
        if name not in self.files:
            self.files.add(name)
            self._write_manifest()
        return self.root / name

    def folder(self, name: str) -> Path:
        """Sub-folder ``name`` of the outputs (created; a symlink there is refused)."""
        _plain_name(name)
        path = self.root / name
        if path.is_symlink():
            raise OutputError(path, "is a symbolic link; refusing to write through it")
        try:
            path.mkdir(exist_ok=True)
        except OSError as exc:
            raise OutputError(path, f"cannot create ({describe_os_error(exc)})") from None
        if name not in self.folders:
            self.folders.add(name)
            self._write_manifest()
        return path

    @contextlib.contextmanager
    def atomic(self, name: str) -> Iterator[Path]:
        """A temporary path that becomes output ``name`` when the block ends without error."""
        with atomic_path(self.path(name)) as temporary:
            yield temporary

    def write_bytes(self, name: str, data: bytes) -> Path:
        path = self.path(name)
        atomic_write_bytes(path, data)
        return path

    def write_text(self, name: str, text: str) -> Path:
        path = self.path(name)
        atomic_write_text(path, text)
        return path

    def write_json(self, name: str, value: Any) -> Path:
        return self.write_text(name, json.dumps(value, indent=2, sort_keys=True) + "\n")
