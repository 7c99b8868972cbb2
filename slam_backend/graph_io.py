"""Pose-graph datasets in, g2o out.

Readers (all through gtsam where gtsam has one):

* ``g2o`` 3D (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``): ``gtsam.readG2o(path, is3D=True)``
* ``g2o`` 2D (``VERTEX_SE2`` / ``EDGE_SE2``): ``gtsam.readG2o(path, is3D=False)``
* TORO 3D (``EDGE3``, e.g. gtsam/Data/sphere2500.txt): ``gtsam.load3D``
* TORO 2D (``VERTEX2`` / ``EDGE2`` with TORO information order, e.g. w10000.graph):
  ``gtsam.load2D(noiseFormat=NoiseFormatTORO)``
* ``city10000`` (gtsam/Data/T1_city10000_04.txt, ``EDGE2 s 1 t 0 n x y theta [x y theta]``): gtsam
  has no reader for it, so it is parsed here. The file has no noise model; ``CITY10000_SIGMAS``
  (0.02 m, 0.02 m, 0.01 rad) match the spread of its odometry against ISAM2_GT_city10000.txt.
  Its 200 two-hypothesis odometry edges keep the first hypothesis (the one that moves forward), so
  the graph is a plain pose graph.

Every file is checked line by line before gtsam reads it (gtsam's stream parser would read a short
line on into the next one, stop silently at an out-of-range number, or build NaN noise models from
information that is not positive definite): the known lines must have exactly their fields, ids
are integers in ``[0, MAX_NODE_ID]``, every number is finite, coordinates and angles are within
``MAX_COORDINATE``, quaternions have unit norm (to 1%, gtsam normalises them), information
matrices are symmetric positive definite with entries within ``MAX_INFORMATION``, edges join two
different nodes and a vertex id appears once. A failed check is a ``GraphFileError`` naming the
file and line. Lines of other tags are skipped, as gtsam skips them; landmark lines (``VERTEX_XY``,
``BR``, ``LANDMARK``, ``VERTEX_TRACKXYZ``) are checked but not used: the problem is a pose graph.

The edges between consecutive node ids form the odometry chain (every node must have one); every
other edge is a loop candidate (a reversed edge ``j -> i`` is inverted). Nodes without an initial
value are initialised by composing the odometry.

Ground truth (``--gt``): a graph file of the same kinds (its vertices, or its odometry composed when
it has none, as sphere2500_groundtruth.txt), a table of ``x y theta`` per node
(ISAM2_GT_city10000.txt), or a TUM / KITTI trajectory.
"""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import gtsam
import numpy as np

from frontends.errors import InputFileError
from frontends.trajectory_io import read_kitti_poses, read_numeric_table, read_tum
from slam_backend.lie import Mode, PoseGroup, as_4x4, pose_group
from slam_backend.problem import LoopCandidate, PoseGraphProblem

GRAPH_FORMATS = ("auto", "g2o", "g2o-2d", "toro-3d", "toro-2d", "city10000")
#: x, y, theta sigmas for city10000 (the file has no noise model): the measured odometry error spread.
CITY10000_SIGMAS = (0.02, 0.02, 0.01)


#: Largest |coordinate| or |angle| a pose-graph line may hold (1e6 km): beyond it the file is wrong.
MAX_COORDINATE = 1e9
#: Largest |entry| of an information matrix (a sigma of ~3e-8): larger ones overflow the squared
#: whitened errors of the optimiser on large residuals.
MAX_INFORMATION = 1e15
#: Largest node id: ids become float timestamps, exact up to 2**53.
MAX_NODE_ID = 2**53 - 1
#: gtsam skips the rest of a line through an 81920-byte buffer and would parse what lies beyond.
MAX_LINE_BYTES = 65536
# What a C++ stream reads as one double (no inf/nan/hex, which fail it) and as a size_t id.
_NUMBER = re.compile(rb"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_ID = re.compile(rb"[0-9]{1,16}")  # 2**53 has 16 digits; int() refuses over 4300


class GraphFileError(InputFileError):
    """A pose-graph file is missing, malformed or not a sequential pose graph."""


@dataclass(frozen=True)
class _LineLayout:
    """The fields after the tag of one kind of line gtsam parses."""

    ids: int
    values: int
    #: Information matrix after the values: "g2o" or "toro" (3x3, 6 entries), "6x6" (21 entries).
    information: str | None = None
    #: Values 3..6 are a quaternion (qx qy qz qw).
    quaternion: bool = False
    #: Namespace in which the first id must be unique (vertices), or None.
    unique: str | None = None
    #: A pose-pose edge: its two ids must differ.
    edge: bool = False

    @cached_property
    def size(self) -> int:
        extra = {"g2o": 6, "toro": 6, "6x6": 21}.get(self.information or "", 0)
        return self.ids + self.values + extra

    @cached_property
    def pattern(self) -> re.Pattern[bytes]:
        """The fields after the tag, joined by single spaces, when every one is well formed."""
        tokens = [_ID.pattern] * self.ids + [_NUMBER.pattern] * (self.size - self.ids)
        return re.compile(b" ".join(tokens))


def _layouts_2d(information: str) -> dict[bytes, _LineLayout]:
    vertex = _LineLayout(1, 3, unique="pose")
    edge = _LineLayout(2, 3, information, edge=True)
    return {
        **dict.fromkeys((b"VERTEX_SE2", b"VERTEX2", b"VERTEX"), vertex),
        **dict.fromkeys((b"EDGE_SE2", b"EDGE2", b"EDGE", b"ODOMETRY"), edge),
        b"VERTEX_XY": _LineLayout(1, 2, unique="landmark"),
        b"BR": _LineLayout(2, 4),
        b"LANDMARK": _LineLayout(2, 5),
    }


_LAYOUTS_3D = {
    b"VERTEX_SE3:QUAT": _LineLayout(1, 7, quaternion=True, unique="pose"),
    b"VERTEX3": _LineLayout(1, 6, unique="pose"),
    b"VERTEX_TRACKXYZ": _LineLayout(1, 3, unique="landmark"),
    b"PARAMS_SE3OFFSET": _LineLayout(1, 7, quaternion=True, unique="offset"),
    b"EDGE_SE3:QUAT": _LineLayout(2, 7, "6x6", quaternion=True, edge=True),
    b"EDGE3": _LineLayout(2, 6, "6x6", edge=True),
    # pose id, landmark id, offset id, x y z, 3x3 information (upper triangle).
    b"EDGE_SE3_TRACKXYZ": _LineLayout(3, 3, "g2o"),
}
#: The lines gtsam's reader of each format parses (``readG2o``/``load3D`` and ``load2D``).
_LAYOUTS = {
    "g2o": _LAYOUTS_3D,
    "toro-3d": _LAYOUTS_3D,
    "g2o-2d": _layouts_2d("g2o"),
    "toro-2d": _layouts_2d("toro"),
}


def _shown(text: bytes | str, limit: int = 40) -> str:
    """``text`` for an error message: decoded, repr-quoted and cut to ``limit`` characters."""
    if isinstance(text, bytes):
        text = text.decode("utf-8", errors="replace")
    return repr(text if len(text) <= limit else text[:limit] + "...")


def _lines(path: Path) -> Iterator[tuple[int, bytes]]:
    """(1-based number, bytes) of every line, split on b"\\n" as gtsam's C++ streams do."""
    try:
        with open(path, "rb") as handle:
            for number in itertools.count(1):
                raw = handle.readline(MAX_LINE_BYTES + 1)
                if not raw:
                    return
                if len(raw) > MAX_LINE_BYTES:
                    raise GraphFileError(path, f"line longer than {MAX_LINE_BYTES} bytes", number)
                yield number, raw
    except FileNotFoundError:
        raise GraphFileError(path, "file not found") from None
    except IsADirectoryError:
        raise GraphFileError(path, "is a folder, not a pose-graph file") from None
    except OSError as exc:
        raise GraphFileError(path, f"cannot read file ({exc.strerror or exc})") from None


def _upper_triangle_index(size: int) -> np.ndarray:
    """Index of each entry of a symmetric matrix in its upper triangle listed row by row."""
    index = np.zeros((size, size), dtype=int)
    index[np.triu_indices(size)] = np.arange(size * (size + 1) // 2)
    return np.maximum(index, index.T)


#: Where each entry of a symmetric information matrix sits in the file's list of its entries.
_INFORMATION_INDEX = {
    "g2o": _upper_triangle_index(3),  # I11 I12 I13 I22 I23 I33
    "toro": np.array([[0, 1, 4], [1, 2, 5], [4, 5, 3]]),  # ff fs ss rr fr sr
    "6x6": _upper_triangle_index(6),
}


def _check_lines(path: Path, fmt: str) -> None:
    """Raise ``GraphFileError`` at the first line of ``path`` gtsam would misread (see the module doc)."""
    layouts = _LAYOUTS[fmt]
    first_line: dict[tuple[str, int], int] = {}
    # Information entries by layout, checked in one batch each (w10000 has 64 000 edges).
    entries: dict[str, list[list[float]]] = {name: [] for name in _INFORMATION_INDEX}
    entry_lines: dict[str, list[tuple[str, int]]] = {name: [] for name in _INFORMATION_INDEX}
    for number, raw in _lines(path):
        fields = raw.split()  # bytes.split: the ASCII whitespace a C++ stream skips
        layout = layouts.get(fields[0]) if fields else None
        if layout is None:
            continue
        tag = fields[0].decode("ascii")
        if len(fields) - 1 != layout.size:
            raise GraphFileError(path, f"{tag} needs {layout.size} values, found {len(fields) - 1}", number)
        if not layout.pattern.fullmatch(b" ".join(fields[1:])):
            raise _bad_token(path, number, tag, fields[1 : 1 + layout.ids], fields[1 + layout.ids :])
        ids = [int(token) for token in fields[1 : 1 + layout.ids]]
        if max(ids) > MAX_NODE_ID:
            raise GraphFileError(path, f"{tag}: id {max(ids)} is not an integer in [0, 2**53)", number)
        numbers = [float(token) for token in fields[1 + layout.ids :]]
        if not all(map(math.isfinite, numbers)):
            raise GraphFileError(path, f"{tag}: number out of range (inf)", number)
        largest = max(map(abs, numbers[: layout.values]))
        if largest > MAX_COORDINATE:
            raise GraphFileError(
                path, f"{tag}: value {largest:.3g} beyond the sane bound {MAX_COORDINATE:g}", number
            )
        if layout.quaternion:
            norm = math.hypot(*numbers[3:7])
            if abs(norm - 1.0) > 0.01:
                raise GraphFileError(path, f"{tag}: quaternion norm {norm:.3g}, expected 1", number)
        if layout.unique is not None:
            key = (layout.unique, ids[0])
            if key in first_line:
                raise GraphFileError(
                    path, f"{tag}: id {ids[0]} already defined on line {first_line[key]}", number
                )
            first_line[key] = number
        if layout.edge and ids[0] == ids[1]:
            raise GraphFileError(path, f"{tag}: edge from node {ids[0]} to itself", number)
        if layout.information is not None:
            information = numbers[layout.values :]
            if max(map(abs, information)) > MAX_INFORMATION:
                raise GraphFileError(
                    path, f"{tag}: information entry beyond the sane bound {MAX_INFORMATION:g}", number
                )
            entries[layout.information].append(information)
            entry_lines[layout.information].append((tag, number))
    # TORO and g2o files both use EDGE2; g2o order read as TORO's is rarely positive definite.
    hint = "; in g2o order? use --graph-format g2o-2d" if fmt == "toro-2d" else ""
    for name, index in _INFORMATION_INDEX.items():
        if entries[name]:
            matrices = np.asarray(entries[name])[:, index]
            _check_positive_definite(path, matrices, entry_lines[name], hint)


def _bad_token(path: Path, number: int, tag: str, ids: list[bytes], numbers: list[bytes]) -> GraphFileError:
    """The error naming the first malformed id or number of a line."""
    for token in ids:
        if not _ID.fullmatch(token):
            return GraphFileError(path, f"{tag}: id {_shown(token)} is not an integer in [0, 2**53)", number)
    bad = next((token for token in numbers if not _NUMBER.fullmatch(token)), b"")
    return GraphFileError(path, f"{tag}: not a number: {_shown(bad)}", number)


def _check_positive_definite(
    path: Path, matrices: np.ndarray, lines: list[tuple[str, int]], hint: str
) -> None:
    eigenvalues = np.linalg.eigvalsh(matrices)
    # Below 1e-12 of the largest eigenvalue, rounding cannot tell the matrix from a singular one.
    bad = np.flatnonzero(eigenvalues[:, 0] <= 1e-12 * np.abs(eigenvalues).max(axis=1))
    if bad.size:
        tag, number = lines[int(bad[0])]
        raise GraphFileError(
            path,
            f"{tag}: information matrix is not positive definite (smallest eigenvalue "
            f"{eigenvalues[bad[0], 0]:.3g}, largest {eigenvalues[bad[0], -1]:.3g}{hint})",
            number,
        )


def detect_format(path: str | Path) -> str:
    """The graph format of ``path`` from its first data line."""
    for number, raw in _lines(Path(path)):
        fields = raw.split()
        if not fields or fields[0].startswith(b"#"):
            continue
        tag = fields[0]
        if tag in (b"VERTEX_SE3:QUAT", b"EDGE_SE3:QUAT"):
            return "g2o"
        if tag in (b"VERTEX_SE2", b"EDGE_SE2"):
            return "g2o-2d"
        if tag in (b"VERTEX3", b"EDGE3"):
            return "toro-3d"
        # "EDGE2 s 1 t 0 n x y theta [...]": a TORO EDGE2 has 12 fields too.
        city = len(fields) in (9, 12) and fields[2] == b"1" and fields[4] == b"0"
        if tag == b"EDGE2" and city and fields[5] in (b"1", b"2"):
            return "city10000"
        if tag in (b"VERTEX2", b"EDGE2"):
            return "toro-2d"
        raise GraphFileError(path, f"unknown pose-graph line tag {_shown(tag)}", number)
    raise GraphFileError(path, "no data lines")


def _read_gtsam(path: Path, fmt: str) -> tuple[Any, Any]:
    _check_lines(path, fmt)
    try:
        if fmt == "g2o":
            return gtsam.readG2o(str(path), True)
        if fmt == "g2o-2d":
            return gtsam.readG2o(str(path), False)
        if fmt == "toro-3d":
            return gtsam.load3D(str(path))
        return gtsam.load2D(str(path), noiseFormat=gtsam.NoiseFormat.NoiseFormatTORO)
    except (RuntimeError, ValueError) as exc:  # std::runtime_error / std::invalid_argument
        raise GraphFileError(path, f"gtsam cannot read it as {fmt} ({_shown(str(exc), 200)})") from None


def _read_city10000(path: Path) -> list[tuple[int, int, np.ndarray]]:
    edges = []
    for number, raw in _lines(path):
        fields = raw.split()
        if not fields:
            continue
        try:
            if not all(_ID.fullmatch(fields[k]) for k in (1, 3, 5)):
                raise ValueError
            start, end, count = int(fields[1]), int(fields[3]), int(fields[5])
            if fields[0] != b"EDGE2" or len(fields) != 6 + 3 * count or count < 1:
                raise ValueError
            x, y, theta = (float(v) for v in fields[6:9])
        except (ValueError, IndexError):
            raise GraphFileError(path, "expected 'EDGE2 s 1 t 0 n x y theta ...'", number) from None
        if not np.isfinite([x, y, theta]).all():
            raise GraphFileError(path, "non-finite value (nan or inf)", number)
        if max(abs(x), abs(y), abs(theta)) > MAX_COORDINATE:
            raise GraphFileError(path, f"value beyond the sane bound {MAX_COORDINATE:g}", number)
        if max(start, end) > MAX_NODE_ID or start == end:
            raise GraphFileError(path, f"edge {start} -> {end}: ids must differ and be below 2**53", number)
        edges.append((start, end, gtsam.Pose2(x, y, theta).matrix()))
    if not edges:
        raise GraphFileError(path, "no data lines")
    return edges


def _edges_of(graph: Any, group: PoseGroup) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    edges = []
    for index in range(graph.size()):
        factor = graph.at(index)
        # Bearing-range factors of landmark lines (BR, LANDMARK) are not part of the pose graph.
        if not isinstance(factor, gtsam.BetweenFactorPose2 | gtsam.BetweenFactorPose3):
            continue
        start, end = (int(k) for k in list(factor.keys()))
        measured = factor.measured()
        noise: Any = factor.noiseModel()  # a Gaussian model (read from an information matrix)
        covariance = np.asarray(noise.covariance(), dtype=np.float64)
        if start > end:
            adjoint = measured.AdjointMap()
            start, end, measured = end, start, measured.inverse()
            covariance = adjoint @ covariance @ adjoint.T
        edges.append((start, end, group.to_matrix(measured), covariance))
    return edges


def read_pose_graph(
    path: str | Path, fmt: str = "auto", sigmas: tuple[float, ...] | None = None
) -> PoseGraphProblem:
    """Read a pose-graph file into a problem whose loops are the dataset's own (all labelled true).

    ``sigmas`` (tangent order of the group, see :mod:`slam_backend.lie`) replace every edge's noise
    model, for files whose information matrices are not their real noise (sphere2500's say 0.32 rad
    per rotation axis, its edges are off by about 0.01-0.04 rad against its ground truth).
    """
    path = Path(path)
    if fmt == "auto":
        fmt = detect_format(path)
    if fmt not in GRAPH_FORMATS:
        raise GraphFileError(path, f"unknown graph format {fmt!r}; use one of {GRAPH_FORMATS}")
    mode: Mode = "se3" if fmt in ("g2o", "toro-3d") else "se2"
    group = pose_group(mode)
    initial: Any = None
    if fmt == "city10000":
        covariance = np.diag(np.square(CITY10000_SIGMAS))
        edges = [(s, t, m, covariance) for s, t, m in _read_city10000(path)]
    else:
        graph, initial = _read_gtsam(path, fmt)
        edges = _edges_of(graph, group)
    if not edges:
        raise GraphFileError(path, "no between-pose edges")
    if sigmas is not None:
        if len(sigmas) != group.dim or not all(0 < v < np.inf for v in sigmas):
            raise GraphFileError(
                path, f"--sigmas needs {group.dim} positive values for {mode}, got {_shown(str(sigmas), 80)}"
            )
        replaced = np.diag(np.square(np.asarray(sigmas, dtype=np.float64)))
        edges = [(s, t, m, replaced) for s, t, m, _ in edges]
    nodes = sorted({k for edge in edges for k in edge[:2]})
    successor = dict(itertools.pairwise(nodes))
    odometry: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    loops = []
    for start, end, matrix, covariance in edges:
        if successor.get(start) == end and end not in odometry:
            odometry[end] = (matrix, covariance)
        else:
            loops.append(LoopCandidate(start, end, matrix, covariance, is_true=True))
    missing = [n for n in nodes[1:] if n not in odometry]
    if missing:
        raise GraphFileError(path, f"no odometry edge into node {missing[0]} (needs a sequential chain)")
    first = nodes[0]
    first_pose = (
        group.to_matrix(group.value_at(initial, first))
        if initial is not None and initial.exists(first)
        else np.eye(group.matrix_size)
    )
    prior_covariance = np.eye(group.dim) * 1e-12
    return PoseGraphProblem(
        name=path.name,
        mode=mode,
        keyframe_ids=nodes,
        odometry=[first_pose] + [odometry[n][0] for n in nodes[1:]],
        odometry_covariances=[prior_covariance] + [odometry[n][1] for n in nodes[1:]],
        loops=loops,
        timestamps=np.asarray(nodes, dtype=np.float64),
    )


def read_ground_truth(path: str | Path, keyframe_ids: list[int]) -> np.ndarray:
    """Ground-truth 4x4 poses of ``keyframe_ids`` (node ids, or row indices of a trajectory file)."""
    path = Path(path)
    first_tag = _first_field(path)  # a number starts a table, a tag a graph file
    if first_tag and not _is_number(first_tag):
        problem = read_pose_graph(path)
        poses = {
            key: as_4x4(pose)
            for key, pose in zip(problem.keyframe_ids, _gt_poses(path, problem), strict=True)
        }
    else:
        table, line_numbers = read_numeric_table(path, (3, 8, 12), error=GraphFileError)
        coordinates = table[:, 1:] if table.shape[1] == 8 else table  # a TUM timestamp may exceed it
        too_large = np.flatnonzero(np.abs(coordinates).max(axis=1) > MAX_COORDINATE)
        if too_large.size:
            raise GraphFileError(
                path, f"value beyond the sane bound {MAX_COORDINATE:g}", int(line_numbers[too_large[0]])
            )
        if table.shape[1] == 3:
            poses = {n: as_4x4(gtsam.Pose2(*row).matrix()) for n, row in enumerate(table)}
        else:
            trajectory = read_tum(path) if table.shape[1] == 8 else read_kitti_poses(path)
            poses = dict(enumerate(trajectory.poses_se3))
    missing = [k for k in keyframe_ids if k not in poses]
    if missing:
        raise GraphFileError(path, f"no ground-truth pose for node {missing[0]} ({len(poses)} poses in file)")
    return np.stack([poses[k] for k in keyframe_ids])


def _first_field(path: Path) -> bytes:
    """The first field of the first line that is neither blank nor a comment (``#``, ``%``)."""
    for _, raw in _lines(path):
        fields = raw.split()
        if fields and not fields[0].startswith((b"#", b"%")):
            return fields[0]
    return b""


def _is_number(text: bytes) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _gt_poses(path: Path, problem: PoseGraphProblem) -> list[np.ndarray]:
    fmt = detect_format(path)
    if fmt != "city10000":
        _, initial = _read_gtsam(path, fmt)
        group = pose_group(problem.mode)
        if all(initial.exists(k) for k in problem.keyframe_ids):
            return [group.to_matrix(group.value_at(initial, k)) for k in problem.keyframe_ids]
    return problem.dead_reckoning()


def write_g2o(path: str | Path, graph: Any, values: Any) -> None:
    """Write a factor graph and its values with ``gtsam.writeG2o`` (SE(2)/SE(3) only)."""
    gtsam.writeG2o(graph, values, str(path))
