"""Pose-graph files from an untrusted source: every bad line is a ``GraphFileError`` naming the file and
line, never a traceback from gtsam or a graph with NaN noise; the real gtsam datasets still read."""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

import gtsam
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from eval.cli import main
from frontends.errors import SymbioError
from slam_backend.graph_io import GraphFileError, read_ground_truth, read_pose_graph
from slam_backend.problem import PoseGraphProblem

GTSAM_DATA = Path(gtsam.__file__).parent / "Data"
INFO_2D = "1 0 0 1 0 1"  # identity, in g2o order
INFO_3D = " ".join("1" if j == i else "0" for i in range(6) for j in range(i, 6))
Q_ID = "0 0 0 1"


def _graph(tmp_path: Path, name: str, lines: list[str]) -> Path:
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _se2_chain(count: int = 3) -> list[str]:
    return [f"EDGE_SE2 {k} {k + 1} 1 0 0 {INFO_2D}" for k in range(count)]


def _se3_chain(count: int = 3) -> list[str]:
    return [f"EDGE_SE3:QUAT {k} {k + 1} 1 0 0 {Q_ID} {INFO_3D}" for k in range(count)]


SE2 = f"EDGE_SE2 0 1 1 0 0 {INFO_2D}"
SE3 = f"EDGE_SE3:QUAT 0 1 1 0 0 {Q_ID} {INFO_3D}"
CITY = "EDGE2 0 1 1 0 1 1 0 0"


@pytest.mark.parametrize(
    ("first", "bad", "message"),
    [
        pytest.param(
            SE2,
            "EDGE_SE2 1 2 1 0 0 -1 0 0 1 0 1",
            "EDGE_SE2: information matrix is not positive definite",
            id="negative SE2 information",
        ),
        pytest.param(
            SE2,
            "EDGE_SE2 1 2 1 0 0 1 5 0 1 0 1",
            r"not positive definite \(smallest eigenvalue -4",
            id="indefinite SE2 information",
        ),
        pytest.param(
            "EDGE2 0 1 1 0 0 1 0 1 1 0 0",
            "EDGE2 1 2 1 0 0 0 0 1 1 0 0",
            "use --graph-format g2o-2d",
            id="zero TORO information (gtsam: ValueError)",
        ),
        pytest.param(
            SE3,
            f"EDGE_SE3:QUAT 1 2 1 0 0 {Q_ID} 1 5 0 0 0 0 {INFO_3D[12:]}",
            "EDGE_SE3:QUAT: information matrix is not positive definite",
            id="indefinite SE3 information",
        ),
        pytest.param(
            f"EDGE3 0 1 1 0 0 0 0 0 {INFO_3D}",
            f"EDGE3 1 2 1 0 0 0 0 0 {INFO_3D[:-1]}0",
            "EDGE3: information matrix is not positive definite",
            id="singular EDGE3 information",
        ),
        pytest.param(
            SE3,
            f"EDGE_SE3:QUAT 1 2 1e308 0 0 {Q_ID} {INFO_3D}",
            r"value 1e\+308 beyond the sane bound",
            id="1e308 translation",
        ),
        pytest.param(SE2, "VERTEX_SE2 0 0 1e308 0", r"VERTEX_SE2: value 1e\+308", id="1e308 vertex"),
        pytest.param(
            SE3,
            f"EDGE_SE3:QUAT 1 2 1e999 0 0 {Q_ID} {INFO_3D}",
            "number out of range",
            id="overflowing number (gtsam stopped reading)",
        ),
        pytest.param(
            SE3,
            f"EDGE_SE3:QUAT 1 2 1 0 0 0 0 0 0 {INFO_3D}",
            "quaternion norm 0, expected 1",
            id="zero quaternion",
        ),
        pytest.param(
            SE3,
            "EDGE_SE3:QUAT 1 2 1 0 0 0 0 0 1 1 0 0",
            "EDGE_SE3:QUAT needs 30 values, found 12",
            id="short line (gtsam read on into the next)",
        ),
        pytest.param(SE2, f"EDGE_SE2 -1 0 1 0 0 {INFO_2D}", "id '-1' is not an integer", id="negative id"),
        pytest.param(SE2, f"EDGE_SE2 1 {'9' * 5000} 1 0 0 {INFO_2D}", r"id '9{40}\.\.\.'", id="huge id"),
        pytest.param(SE2, f"EDGE_SE2 1 1 1 0 0 {INFO_2D}", "edge from node 1 to itself", id="self edge"),
        pytest.param(
            "VERTEX_SE2 0 0 0 0",
            "VERTEX_SE2 0 1 0 0",
            "id 0 already defined on line 1",
            id="duplicate vertex",
        ),
        pytest.param(
            SE2, f"EDGE_SE2 1 2 0x10 0 0 {INFO_2D}", "not a number: '0x10'", id="hexadecimal number"
        ),
        pytest.param(
            SE2,
            "EDGE_SE2 1 2 1 0 0 1e300 0 0 1 0 1",
            "information entry beyond the sane bound",
            id="huge information",
        ),
        pytest.param(CITY, "EDGE2 1 1 1 0 1 1 0 0", "ids must differ", id="city10000 self edge"),
        pytest.param(CITY, "EDGE2 1 1 2 0 1 1e300 0 0", "sane bound", id="city10000 huge value"),
    ],
)
def test_bad_line_is_an_error_naming_file_and_line(
    tmp_path: Path, first: str, bad: str, message: str
) -> None:
    path = _graph(tmp_path, "bad.graph", [first, bad])
    with pytest.raises(GraphFileError, match=message) as raised:
        read_pose_graph(path)
    assert str(raised.value).startswith(f"{path}:2: ")
    assert len(str(raised.value)) < len(str(path)) + 200


def test_text_beyond_gtsam_line_buffer_is_refused(tmp_path: Path) -> None:
    # gtsam skips the rest of a line through an 81920-byte buffer: the edge at the end of this comment
    # would have been read as a loop closure.
    hidden = "# " + " " * 90_000 + f"EDGE_SE2 0 3 5 5 0 {INFO_2D}"
    path = _graph(tmp_path, "hidden.g2o", [*_se2_chain(3), hidden])
    with pytest.raises(GraphFileError, match=r"hidden\.g2o:4: line longer than 65536 bytes"):
        read_pose_graph(path)


def test_landmark_lines_are_skipped(tmp_path: Path) -> None:
    # A TORO file with bearing-range lines, as gtsam's example.graph: the bearing-range factors are
    # not pose edges (they used to fail with an AttributeError).
    problem = read_pose_graph(GTSAM_DATA / "example.graph")
    assert problem.mode == "se2" and len(problem.keyframe_ids) == 95
    lines = [*_se2_chain(2), "VERTEX_XY 7 1 2", "BR 1 7 0.5 2.0 0.1 0.1", "BR 1 7 0.5"]
    with pytest.raises(GraphFileError, match=r"br\.graph:5: BR needs 6 values, found 3"):
        read_pose_graph(_graph(tmp_path, "br.graph", lines), "g2o-2d")


def test_gtsam_datasets_read_and_a_misread_order_is_named() -> None:
    # The checks refuse none of gtsam's own datasets (given their format)...
    for name, fmt, nodes in [
        ("sphere2500.txt", "toro-3d", 2500),
        ("w100.graph", "toro-2d", 100),
        ("pose3example-grid.txt", "g2o", 27),
        ("noisyToyGraph.txt", "g2o-2d", 4),
        ("T1_city10000_04.txt", "city10000", 10000),
        ("w20000.txt", "g2o-2d", 20061),
    ]:
        problem = read_pose_graph(GTSAM_DATA / name, fmt)
        assert len(problem.keyframe_ids) == nodes
        assert all(np.isfinite(c).all() for c in problem.odometry_covariances)
    # ...and w20000.txt, whose EDGE2 tag (TORO's) carries g2o's information order, gets a hint (gtsam
    # raised a ValueError).
    with pytest.raises(GraphFileError, match=r"w20000\.txt:1: .*use --graph-format g2o-2d"):
        read_pose_graph(GTSAM_DATA / "w20000.txt")


def test_ground_truth_checks(tmp_path: Path) -> None:
    table = _graph(tmp_path, "gt.txt", ["0 0 0", "1 0 0", "1e300 0 0"])
    with pytest.raises(GraphFileError, match=r"gt\.txt:3: value beyond the sane bound"):
        read_ground_truth(table, [0, 1, 2])
    # A commented TUM header: the file is a trajectory, not a graph with an unknown tag.
    tum = _graph(
        tmp_path, "gt_tum.txt", ["# timestamp tx ty tz qx qy qz qw", "1.0 0 0 0 0 0 0 1", "2.0 1 0 0 0 0 0 1"]
    )
    np.testing.assert_allclose(read_ground_truth(tum, [0, 1])[:, 0, 3], [0.0, 1.0])
    # A 3D graph whose landmarks outnumber its missing pose vertices: the missing ones are composed.
    graph = _graph(
        tmp_path,
        "gt.g2o",
        [
            f"VERTEX_SE3:QUAT 0 0 0 0 {Q_ID}",
            "VERTEX_TRACKXYZ 0 5 5 5",
            "VERTEX_TRACKXYZ 1 6 6 6",
            *_se3_chain(2),
        ],
    )
    np.testing.assert_allclose(read_ground_truth(graph, [0, 1, 2])[:, 0, 3], [0.0, 1.0, 2.0])


def test_posegraph_command_prints_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _graph(tmp_path, "neg.g2o", [*_se2_chain(1), "EDGE_SE2 1 2 1 0 0 -1 0 0 1 0 1"])
    assert main(["posegraph", "--g2o", str(path)]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1
    assert error.startswith(f"symbio: error: {path}:2: EDGE_SE2: information matrix is not positive definite")
    with pytest.raises(SystemExit):
        main(["posegraph", "--g2o", str(path), "--sigmas", "1,x,1"])
    assert "--sigmas: expected comma-separated numbers, got '1,x,1'" in capsys.readouterr().err
    assert main(["posegraph", "--g2o", str(GTSAM_DATA / "pose2example.txt"), "--sigmas", "nan,1,1"]) == 2
    assert "--sigmas needs 3 positive values" in capsys.readouterr().err


# --- fuzzing -------------------------------------------------------------------------------------

FUZZ = settings(
    max_examples=10_000 if os.environ.get("HYPOTHESIS_PROFILE") == "fuzz" else 150,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
TOKENS = ["0", "1", "-1", "0.5", "1e3", "1e308", "1e999", "-1e999", "nan", "inf", "abc", "", "0x10", "3.",
          ".5", "1e", "--1", "1_000", "9" * 30, "1e-320", "\t", "é", "#"]  # fmt: skip
TAGS = ["VERTEX_SE2", "EDGE_SE2", "VERTEX2", "EDGE2", "VERTEX3", "EDGE3", "VERTEX_SE3:QUAT", "EDGE_SE3:QUAT",
        "VERTEX_XY", "BR", "LANDMARK", "ODOMETRY", "VERTEX_TRACKXYZ", "EDGE_SE3_TRACKXYZ", "PARAMS_SE3OFFSET",
        "EQUIV", "FIX", "#"]  # fmt: skip


def _row(family: str, start: int, end: int, pose: list[float], info: list[float]) -> str:
    """A valid line of ``family`` for the edge ``start -> end`` (a vertex when ``end`` < 0)."""
    x, y, z, angle = pose
    q = f"0 0 {math.sin(angle / 2):.9g} {math.cos(angle / 2):.9g}"
    a, b, c = (f"{v:.6g}" for v in info)
    info_2d = f"{a} 0 {b} {c} 0 0" if family == "toro-2d" else f"{a} 0 0 {b} 0 {c}"  # diagonal
    info_3d = " ".join(f"{(a, b, c)[i % 3] if j == i else 0}" for i in range(6) for j in range(i, 6))
    if family == "g2o":
        if end < 0:
            return f"VERTEX_SE3:QUAT {start} {x:.6g} {y:.6g} {z:.6g} {q}"
        return f"EDGE_SE3:QUAT {start} {end} {x:.6g} {y:.6g} {z:.6g} {q} {info_3d}"
    if family == "toro-3d":
        if end < 0:
            return f"VERTEX3 {start} {x:.6g} {y:.6g} {z:.6g} 0 0 {angle:.6g}"
        return f"EDGE3 {start} {end} {x:.6g} {y:.6g} {z:.6g} 0 0 {angle:.6g} {info_3d}"
    if family == "city10000":
        return f"EDGE2 {start} 1 {max(end, start + 1)} 0 1 {x:.6g} {y:.6g} {angle:.6g}"
    tag = ("VERTEX_SE2", "EDGE_SE2") if family == "g2o-2d" else ("VERTEX2", "EDGE2")
    if end < 0:
        return f"{tag[0]} {start} {x:.6g} {y:.6g} {angle:.6g}"
    return f"{tag[1]} {start} {end} {x:.6g} {y:.6g} {angle:.6g} {info_2d}"


@st.composite
def graph_files(draw: st.DrawFn) -> tuple[str, str]:
    """A valid pose graph of one format (a chain, loops, vertices), then a few mutations of its lines."""
    family = draw(st.sampled_from(["g2o", "g2o-2d", "toro-2d", "toro-3d", "city10000"]))
    count = draw(st.integers(2, 6))
    pose = st.lists(st.floats(-100, 100), min_size=4, max_size=4)
    info = st.lists(st.floats(0.01, 1e4), min_size=3, max_size=3)
    pairs = [(k, k + 1) for k in range(count - 1)]
    pairs += draw(st.lists(st.tuples(st.integers(0, count - 1), st.integers(0, count - 1)), max_size=3))
    pairs += [(k, -1) for k in draw(st.sets(st.integers(0, count - 1), max_size=count))]
    lines = [_row(family, s, e, draw(pose), draw(info)) for s, e in pairs if s != e]
    for _ in range(draw(st.integers(0, 3))):
        index = draw(st.integers(0, len(lines)))
        kind = draw(st.sampled_from(["token", "token", "drop", "extra", "tag", "garbage", "crlf"]))
        fields = lines[index].split(" ") if index < len(lines) else [draw(st.sampled_from(TAGS))]
        position = draw(st.integers(0, len(fields) - 1))
        if kind == "token":
            fields[position] = draw(st.sampled_from(TOKENS))
        elif kind == "drop":
            del fields[position]
        elif kind == "extra":
            fields.insert(position, draw(st.sampled_from(TOKENS)))
        elif kind == "tag":
            fields[0] = draw(st.sampled_from(TAGS))
        elif kind == "garbage":
            fields = [draw(st.text(max_size=30))]
        else:
            fields[-1] += "\r"
        if index < len(lines):
            lines[index] = " ".join(fields)
        else:
            lines.append(" ".join(fields))
    return family, "\n".join(lines) + "\n"


def _assert_sound(problem: PoseGraphProblem) -> None:
    """What the backend may rely on: finite transforms, symmetric positive-definite covariances."""
    covariances = [*problem.odometry_covariances[1:], *(loop.covariance for loop in problem.loops)]
    transforms = [*problem.odometry, *(loop.relative for loop in problem.loops)]
    assert all(np.isfinite(t).all() for t in transforms)
    for covariance in covariances:
        assert np.isfinite(covariance).all()
        np.testing.assert_allclose(covariance, covariance.T, atol=1e-12 * np.abs(covariance).max())
        assert np.linalg.eigvalsh(covariance)[0] > 0


@FUZZ
@given(graph_files(), st.booleans())
def test_fuzzed_graph_files_read_soundly_or_name_file_and_line(
    tmp_path: Path, drawn: tuple[str, str], auto: bool
) -> None:
    family, text = drawn
    folder = tmp_path / "input"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir()
    path = folder / "fuzz.graph"
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    try:
        problem = read_pose_graph(path, "auto" if auto else family)
    except SymbioError as exc:
        assert str(exc).startswith(str(path)), f"error does not name the file: {exc}"
        assert len(str(exc)) < len(str(path)) + 300
        return
    _assert_sound(problem)
