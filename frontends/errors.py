"""The project's documented error types.

Every error caused by user input names the file (and the line, where there is one) so the user can
fix it without reading a traceback from inside numpy or OpenCV.
"""

from __future__ import annotations

from pathlib import Path


class SymbioError(Exception):
    """Base of every error this project raises on purpose."""


class InputFileError(SymbioError):
    """A user-supplied file is missing, unreadable or malformed."""

    def __init__(self, path: str | Path, message: str, line: int | None = None) -> None:
        self.path = str(path)
        self.line = line
        self.reason = message
        where = f"{self.path}:{line}" if line is not None else self.path
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


class ConfigError(SymbioError):
    """A configuration value or YAML config file is invalid."""


class ModelError(InputFileError):
    """A model file (network weights or graph) is missing, unreadable, or fails when run."""
