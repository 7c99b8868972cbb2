"""The project's documented error types.

Every error caused by user input names the file (and the line, where there is one) so the user can
fix it without reading a traceback from inside numpy or OpenCV.
"""

from __future__ import annotations

import os
from pathlib import Path


def display_path(path: str | Path) -> str:
    """``path`` as printable text: the bytes of a name that is not UTF-8 as ``\\xNN`` escapes.

    Python keeps such bytes as lone surrogates, which a UTF-8 stream (stdout, a log file) refuses."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


class SymbioError(Exception):
    """Base of every error this project raises on purpose."""


class InputFileError(SymbioError):
    """A user-supplied file is missing, unreadable or malformed."""

    def __init__(self, path: str | Path, message: str, line: int | None = None) -> None:
        self.path = str(path)
        self.line = line
        self.reason = message
        shown = display_path(self.path)
        where = f"{shown}:{line}" if line is not None else shown
        super().__init__(f"{where}: {message}")

    def __reduce__(self) -> tuple[type[InputFileError], tuple[str, str, int | None]]:
        # Benchmarks run scenes in worker processes; the default pickling passes only the formatted
        # message back to __init__, which then fails and the pool reports a broken process instead.
        return type(self), (self.path, self.reason, self.line)


class DatasetError(InputFileError):
    """A dataset folder or one of its index files is malformed."""


class CalibrationError(InputFileError):
    """Camera intrinsics are missing or invalid."""


class TrajectoryFileError(InputFileError):
    """A TUM/KITTI/EuRoC trajectory file is malformed."""


class OutputError(SymbioError):
    """An output file or folder cannot be written, or writing there would not be safe."""

    def __init__(self, path: str | Path, message: str) -> None:
        self.path = str(path)
        self.reason = message
        super().__init__(f"{display_path(self.path)}: {message}")

    def __reduce__(self) -> tuple[type[OutputError], tuple[str, str]]:
        return type(self), (self.path, self.reason)


class ConfigError(SymbioError):
    """A configuration value or YAML config file is invalid."""


class ModelError(InputFileError):
    """A model file (network weights or graph) is missing, unreadable, or fails when run."""
