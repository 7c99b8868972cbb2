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

The edges between consecutive node ids form the odometry chain (every node must have one); every
other edge is a loop candidate (a reversed edge ``j -> i`` is inverted). Nodes without an initial
value are initialised by composing the odometry.

Ground truth (``--gt``): a graph file of the same kinds (its vertices, or its odometry composed when
it has none, as sphere2500_groundtruth.txt), a table of ``x y theta`` per node
(ISAM2_GT_city10000.txt), or a TUM / KITTI trajectory.
"""

from __future__ import annotations

import itertools
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


class GraphFileError(InputFileError):
    """A pose-graph file is missing, malformed or not a sequential pose graph."""


def detect_format(path: str | Path) -> str:
    """The graph format of ``path`` from its first data line."""
    try:
        with open(path, encoding="utf-8") as handle:
            for raw in handle:
                fields = raw.split()
                if not fields or fields[0].startswith("#"):
                    continue
                tag = fields[0]
                if tag in ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT"):
                    return "g2o"
                if tag in ("VERTEX_SE2", "EDGE_SE2"):
                    return "g2o-2d"
                if tag in ("VERTEX3", "EDGE3"):
                    return "toro-3d"
                if tag == "EDGE2" and len(fields) in (9, 12) and fields[5] in ("1", "2"):
                    return "city10000"
                if tag in ("VERTEX2", "EDGE2"):
                    return "toro-2d"
                raise GraphFileError(path, f"unknown pose-graph line tag {tag!r}")
    except FileNotFoundError:
        raise GraphFileError(path, "file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise GraphFileError(path, f"cannot read file ({exc})") from None
    raise GraphFileError(path, "no data lines")


def _read_gtsam(path: Path, fmt: str) -> tuple[Any, Any]:
    try:
        if fmt == "g2o":
            return gtsam.readG2o(str(path), True)
        if fmt == "g2o-2d":
            return gtsam.readG2o(str(path), False)
        if fmt == "toro-3d":
            return gtsam.load3D(str(path))
        return gtsam.load2D(str(path), noiseFormat=gtsam.NoiseFormat.NoiseFormatTORO)
    except RuntimeError as exc:
        raise GraphFileError(path, f"gtsam cannot read it as {fmt} ({exc})") from None


def _read_city10000(path: Path) -> list[tuple[int, int, np.ndarray]]:
    edges = []
    with open(path, encoding="utf-8") as handle:
        for number, raw in enumerate(handle, start=1):
            fields = raw.split()
            if not fields:
                continue
            try:
                start, end, count = int(fields[1]), int(fields[3]), int(fields[5])
                if fields[0] != "EDGE2" or len(fields) != 6 + 3 * count or count < 1:
                    raise ValueError
                x, y, theta = (float(v) for v in fields[6:9])
            except (ValueError, IndexError):
                raise GraphFileError(path, "expected 'EDGE2 s 1 t 0 n x y theta ...'", number) from None
            if not np.isfinite([x, y, theta]).all():
                raise GraphFileError(path, "non-finite value (nan or inf)", number)
            edges.append((start, end, gtsam.Pose2(x, y, theta).matrix()))
    if not edges:
        raise GraphFileError(path, "no data lines")
    return edges


def _edges_of(graph: Any, group: PoseGroup) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    edges = []
    for index in range(graph.size()):
        factor = graph.at(index)
        if not hasattr(factor, "measured") or len(factor.keys()) != 2:
            continue
        start, end = (int(k) for k in list(factor.keys()))
        measured = factor.measured()
        covariance = np.asarray(factor.noiseModel().covariance(), dtype=np.float64)
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
        if len(sigmas) != group.dim or min(sigmas) <= 0:
            raise GraphFileError(path, f"--sigmas needs {group.dim} positive values for {mode}, got {sigmas}")
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
    first_tag = ""
    try:
        with open(path, encoding="utf-8") as handle:
            first_tag = next((line.split()[0] for line in handle if line.strip()), "")
    except FileNotFoundError:
        raise GraphFileError(path, "file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise GraphFileError(path, f"cannot read file ({exc})") from None
    if first_tag and not _is_number(first_tag):
        problem = read_pose_graph(path)
        poses = {
            key: as_4x4(pose)
            for key, pose in zip(problem.keyframe_ids, _gt_poses(path, problem), strict=True)
        }
    else:
        table, _ = read_numeric_table(path, (3, 8, 12), error=GraphFileError)
        if table.shape[1] == 3:
            poses = {n: as_4x4(gtsam.Pose2(*row).matrix()) for n, row in enumerate(table)}
        else:
            trajectory = read_tum(path) if table.shape[1] == 8 else read_kitti_poses(path)
            poses = dict(enumerate(trajectory.poses_se3))
    missing = [k for k in keyframe_ids if k not in poses]
    if missing:
        raise GraphFileError(path, f"no ground-truth pose for node {missing[0]} ({len(poses)} poses in file)")
    return np.stack([poses[k] for k in keyframe_ids])


def _is_number(text: str) -> bool:
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
        if initial.size() >= len(problem.keyframe_ids):
            return [group.to_matrix(group.value_at(initial, k)) for k in problem.keyframe_ids]
    return problem.dead_reckoning()


def write_g2o(path: str | Path, graph: Any, values: Any) -> None:
    """Write a factor graph and its values with ``gtsam.writeG2o`` (SE(2)/SE(3) only)."""
    gtsam.writeG2o(graph, values, str(path))
