"""Writing output files so that a reader never sees half of one and no symlink is followed.

Every file is written to a fresh temporary name beside its final name (created exclusively, so an
existing symlink there is never opened), flushed and fsynced, then renamed over the final name:
``rename`` replaces a symlink at the final name instead of writing through it, and a kill at any
moment leaves either the old file or the new one. Failures (disk full, read-only folder, a folder
where a file should be) raise ``OutputError`` naming the file, never a bare ``OSError``.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from frontends.errors import OutputError

#: Prefix of the temporary files (hidden, and recognisable as ours when a killed run left one).
TEMP_PREFIX = ".symbio-tmp-"


def describe_os_error(exc: OSError) -> str:
    """A short reason for ``exc``, with a hint for the cases a user can fix."""
    reason = exc.strerror or str(exc)
    if exc.errno == errno.ENOSPC:
        return f"{reason}: free some space and run again"
    if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        return f"{reason}: choose a folder you can write to"
    return reason


def _fsync_folder(folder: Path) -> None:
    with contextlib.suppress(OSError):  # some file systems cannot fsync a folder; the rename stands
        handle = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(handle)
        finally:
            os.close(handle)


@contextlib.contextmanager
def atomic_path(path: str | Path, *, fsync: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; when the block ends without error the file written
    there replaces ``path`` (a symlink at ``path`` is replaced, not followed). On any error the
    temporary file is removed and ``path`` is left as it was."""
    final = Path(path)
    folder = final.parent
    try:
        handle, name = tempfile.mkstemp(prefix=TEMP_PREFIX + final.name + ".", dir=folder)
    except OSError as exc:
        raise OutputError(final, f"cannot write ({describe_os_error(exc)})") from None
    os.close(handle)
    temporary = Path(name)
    try:
        yield temporary
        if fsync:
            with temporary.open("rb+") as stream:
                os.fsync(stream.fileno())
        if final.is_dir() and not final.is_symlink():
            raise OutputError(final, "is a folder; cannot write a file there")
        os.replace(temporary, final)
    except OSError as exc:
        raise OutputError(final, f"cannot write ({describe_os_error(exc)})") from None
    finally:
        temporary.unlink(missing_ok=True)
    if fsync:
        _fsync_folder(folder)


def atomic_write_bytes(path: str | Path, data: bytes, *, fsync: bool = True) -> None:
    """Write ``data`` to ``path`` atomically (see ``atomic_path``)."""
    with atomic_path(path, fsync=fsync) as temporary:
        try:
            temporary.write_bytes(data)
        except OSError as exc:
            raise OutputError(path, f"cannot write ({describe_os_error(exc)})") from None


def atomic_write_text(path: str | Path, text: str, *, fsync: bool = True) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (see ``atomic_path``)."""
    # A lone surrogate (a file name that is not UTF-8, quoted in a report) is written as \udcNN.
    atomic_write_bytes(path, text.encode("utf-8", "backslashreplace"), fsync=fsync)


def file_sha256(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes, read in 1 MiB blocks (OSError when it cannot be read)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(1 << 20):
            digest.update(block)
    return digest.hexdigest()
