"""Reading and writing TUM / KITTI trajectory files as evo trajectories.

Reading validates every line first (column count, numbers, finite values, unit quaternions,
increasing timestamps; a repeated timestamp keeps its first pose) so a malformed file fails with
its path and line number; evo's own readers report neither. Writing uses evo's writers unchanged.
"""

from __future__ import annotations

import logging
import reprlib
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from evo.core.trajectory import PosePath3D, PoseTrajectory3D
from evo.tools import file_interface

from frontends.errors import InputFileError, TrajectoryFileError

log = logging.getLogger(__name__)

TRAJECTORY_FORMATS = ("tum", "kitti")


def read_numeric_table(
    path: str | Path,
    columns: int | Sequence[int],
    error: type[InputFileError] = TrajectoryFileError,
    delimiter: str | None = None,
    allow_empty: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Parse a whitespace (or ``delimiter``) separated numeric table; ``#`` starts a comment line.

    Returns the (N, C) float matrix and the 1-based line number of every row.
    """
    path = Path(path)
    allowed = (columns,) if isinstance(columns, int) else tuple(columns)
    try:
        with open(path, encoding="utf-8-sig") as handle:
            text = handle.read()
    except FileNotFoundError:
        raise error(path, "file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(path, f"cannot read file ({exc})") from None
    if delimiter is None:
        fast = _whitespace_table(path, text, allowed)
        if fast is not None:
            return fast
    text_lines = text.splitlines()
    rows: list[list[float]] = []
    line_numbers: list[int] = []
    width = None
    for number, raw in enumerate(text_lines, start=1):
        line = raw.strip()
        if not line or line.startswith(("#", "%")):
            continue
        fields = [f for f in (line.split(delimiter) if delimiter else line.split()) if f.strip() != ""]
        if len(fields) not in allowed:
            expected = " or ".join(str(c) for c in allowed)
            raise error(path, f"expected {expected} numbers, found {len(fields)}", number)
        if width is not None and len(fields) != width:
            raise error(path, f"expected {width} numbers like the lines before, found {len(fields)}", number)
        width = len(fields)
        try:
            values = [float(f) for f in fields]
        except ValueError:
            bad = next(f for f in fields if not _is_float(f))
            raise error(path, f"not a number: {reprlib.repr(bad)}", number) from None  # bounded: may be huge
        if not all(np.isfinite(values)):
            raise error(path, "non-finite value (nan or inf)", number)
        rows.append(values)
        line_numbers.append(number)
    if not rows:
        if allow_empty:
            return np.zeros((0, min(allowed))), np.zeros(0, dtype=np.int64)
        raise error(path, "no data lines")
    return np.asarray(rows, dtype=np.float64), np.asarray(line_numbers)


def _whitespace_table(
    path: Path, text: str, allowed: tuple[int, ...]
) -> tuple[np.ndarray, np.ndarray] | None:
    """``read_numeric_table``'s result for a plain whitespace table, parsed by NumPy's C reader
    (the GT loop pairs of a 9000-frame scene: 2.2 M lines, 0.7 GB and 20 s line by line); None for
    anything unusual, which the line-by-line parser then reads or reports with its line number."""
    buffer = np.frombuffer(text.encode("utf-8"), dtype=np.uint8)
    control = np.ones(256, dtype=bool)
    control[32:] = False
    control[[9, 10, 13]] = False
    if len(buffer) == 0 or control[buffer].any():
        return None  # other line breaks or control characters
    starts = np.r_[0, np.flatnonzero(buffer == 10) + 1]
    starts = starts[starts < len(buffer)]
    first = buffer[starts]
    if ((first == 9) | (first == 32)).any():
        return None  # indented lines
    comment = (first == ord("#")) | (first == ord("%"))
    data = ~comment & (first != 10) & (first != 13)
    marks = np.flatnonzero((buffer == ord("#")) | (buffer == ord("%")))
    if not data.any() or data[np.searchsorted(starts, marks, side="right") - 1].any():
        return None  # a comment after numbers
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            table = np.loadtxt(path, dtype=np.float64, comments=("#", "%"), ndmin=2, encoding="utf-8-sig")
    except (ValueError, OSError):
        return None
    if len(table) != data.sum() or table.shape[1] not in allowed or not np.isfinite(table).all():
        return None
    return table, np.flatnonzero(data) + 1


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def check_increasing(
    path: str | Path, stamps: np.ndarray, lines: np.ndarray, error: type[InputFileError] = TrajectoryFileError
) -> None:
    """Raise naming the first line whose timestamp is not after the previous one."""
    steps = np.diff(stamps)
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        k = int(bad[0]) + 1
        kind = "duplicate" if steps[k - 1] == 0 else "decreasing"
        raise error(
            path,
            f"{kind} timestamp {float(stamps[k])!r} "
            f"(previous line {int(lines[k - 1])}: {float(stamps[k - 1])!r})",
            int(lines[k]),
        )


def drop_duplicate_stamps(path: str | Path, stamps: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """Rows to keep of a pose stream: a repeated timestamp keeps its first pose (with a warning).

    Real ground-truth files contain such repeats (TUM fr2/desk has one), so they are not an error
    there; a decreasing timestamp still is.
    """
    keep = np.ones(len(stamps), dtype=bool)
    keep[1:] = np.diff(stamps) != 0
    if not keep.all():
        first = int(lines[np.flatnonzero(~keep)[0]])
        log.warning(
            "%s:%d: %d repeated timestamps, keeping the first pose of each", path, first, (~keep).sum()
        )
    check_increasing(path, stamps[keep], lines[keep])
    return keep


def _check_quaternions(path: str | Path, quat_xyzw: np.ndarray, lines: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(quat_xyzw, axis=1)
    bad = np.flatnonzero(np.abs(norms - 1.0) > 1e-2)
    if bad.size:
        k = int(bad[0])
        raise TrajectoryFileError(path, f"quaternion is not unit length (norm {norms[k]:.4f})", int(lines[k]))
    return quat_xyzw / norms[:, None]


def read_tum(path: str | Path) -> PoseTrajectory3D:
    """TUM format: ``timestamp tx ty tz qx qy qz qw`` per line."""
    table, lines = read_numeric_table(path, 8)
    keep = drop_duplicate_stamps(path, table[:, 0], lines)
    table, lines = table[keep], lines[keep]
    quat = _check_quaternions(path, table[:, 4:8], lines)
    return PoseTrajectory3D(
        positions_xyz=table[:, 1:4], orientations_quat_wxyz=np.roll(quat, 1, axis=1), timestamps=table[:, 0]
    )


def read_kitti_poses(path: str | Path, timestamps: np.ndarray | None = None) -> PoseTrajectory3D:
    """KITTI format: the first 3 rows of a 4x4 camera-to-world pose, row-major, 12 numbers per line.

    KITTI pose files carry no time; ``timestamps`` (e.g. from ``times.txt``) or frame indices are used.
    """
    table, lines = read_numeric_table(path, 12)
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    poses[:, :3, :4] = table.reshape(-1, 3, 4)
    rotations = poses[:, :3, :3]
    orthogonality = np.abs(rotations @ rotations.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero(orthogonality > 1e-2)
    if bad.size:
        raise TrajectoryFileError(path, "rotation part is not orthonormal", int(lines[bad[0]]))
    if timestamps is None:
        timestamps = np.arange(len(poses), dtype=np.float64)
    elif len(timestamps) != len(poses):
        raise TrajectoryFileError(path, f"{len(poses)} poses but {len(timestamps)} timestamps")
    # evo's PosePath3D re-orthonormalises through quaternions; build via the path for exactness.
    path3d = PosePath3D(poses_se3=list(poses))
    return PoseTrajectory3D(poses_se3=path3d.poses_se3, timestamps=np.asarray(timestamps, dtype=np.float64))


def read_times(path: str | Path, error: type[InputFileError] = TrajectoryFileError) -> np.ndarray:
    """A ``times.txt`` file: one timestamp (s) per line, strictly increasing."""
    table, lines = read_numeric_table(path, 1, error)
    stamps = table[:, 0]
    check_increasing(path, stamps, lines, error)
    return stamps


def read_trajectory(path: str | Path, fmt: str) -> PoseTrajectory3D:
    if fmt == "tum":
        return read_tum(path)
    if fmt == "kitti":
        return read_kitti_poses(path)
    raise TrajectoryFileError(path, f"unknown trajectory format {fmt!r}; use one of {TRAJECTORY_FORMATS}")


def write_trajectory(path: str | Path, trajectory: PoseTrajectory3D, fmt: str = "tum") -> None:
    if fmt == "tum":
        file_interface.write_tum_trajectory_file(str(path), trajectory)
    elif fmt == "kitti":
        file_interface.write_kitti_poses_file(str(path), trajectory)
    else:
        raise ValueError(f"unknown trajectory format {fmt!r}")
