from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from evo.core.trajectory import PoseTrajectory3D
from evo.tools import file_interface

from frontends.errors import TrajectoryFileError
from frontends.trajectory_io import (
    read_kitti_poses,
    read_numeric_table,
    read_times,
    read_tum,
    write_trajectory,
)

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw\n"


def _random_trajectory(n: int, seed: int = 0) -> PoseTrajectory3D:
    rng = np.random.default_rng(seed)
    quat = rng.normal(size=(n, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    return PoseTrajectory3D(rng.normal(size=(n, 3)), quat, np.arange(n) * 0.1 + 1.0)


def test_tum_round_trip_matches_evo(tmp_path: Path) -> None:
    path = tmp_path / "traj.txt"
    original = _random_trajectory(20)
    write_trajectory(path, original, "tum")
    ours = read_tum(path)
    theirs = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_allclose(ours.positions_xyz, theirs.positions_xyz)
    np.testing.assert_allclose(
        np.abs(ours.orientations_quat_wxyz), np.abs(theirs.orientations_quat_wxyz), atol=1e-7
    )
    np.testing.assert_allclose(ours.timestamps, original.timestamps)


def test_tum_accepts_tabs_and_double_spaces(tmp_path: Path) -> None:
    path = tmp_path / "t.txt"
    path.write_text(TUM_HEADER + "1.0\t0 0  0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n")
    assert read_tum(path).num_poses == 2


@pytest.mark.parametrize(
    ("body", "line", "message"),
    [
        ("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n", 3, "expected 8 numbers, found 7"),
        ("1.0 0 0 0 0 0 0 1\n2.0 0 0 x 0 0 0 1\n", 3, "not a number: 'x'"),
        ("1.0 0 0 0 0 0 0 1\n2.0 0 0 nan 0 0 0 1\n", 3, "non-finite"),
        ("2.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1\n", 3, "decreasing timestamp"),
        ("1.0 0 0 0 0 0 0 2\n", 2, "not unit length"),
    ],
)
def test_tum_errors_name_file_and_line(tmp_path: Path, body: str, line: int, message: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(TUM_HEADER + body)
    with pytest.raises(TrajectoryFileError, match=rf"bad\.txt:{line}: .*{message}"):
        read_tum(path)


@pytest.mark.parametrize(
    "body",
    [
        "# pairs\n1 2\n\n% note\n3 4\r\n5 6",  # comments, a blank line, CRLF, no final newline
        "1 2\n  3 4\n",  # indented: read line by line
        "1 2 # a comment after numbers is not allowed\n",
        "1 2\n3\n",
        "1 2\n3 x\n",
        "1 2\n3 inf\n",
        "\ufeff1 2\n3 4\n",  # a byte-order mark
    ],
)
def test_numpy_and_line_by_line_readers_agree(tmp_path: Path, body: str) -> None:
    """Plain tables go through NumPy's reader (a 2.2 M-line GT pairs file: 20 s -> 2 s); anything
    unusual is read, or refused with its line, by the line-by-line parser, with the same results."""
    path = tmp_path / "table.txt"
    path.write_bytes(body.encode("utf-8"))
    outcomes = []
    for delimiter in (None, " "):  # a delimiter always reads line by line
        try:
            table, lines = read_numeric_table(path, 2, delimiter=delimiter)
            outcomes.append((table.tolist(), lines.tolist()))
        except TrajectoryFileError as error:
            outcomes.append(str(error))
    assert outcomes[0] == outcomes[1]
    if body.startswith("#"):
        assert outcomes[0] == ([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]], [2, 5, 6])


def test_repeated_timestamp_keeps_first_pose(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / "gt.txt"
    path.write_text(TUM_HEADER + "1.0 0 0 0 0 0 0 1\n1.0 5 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n")
    trajectory = read_tum(path)
    np.testing.assert_allclose(trajectory.positions_xyz[:, 0], [0, 1])
    assert "gt.txt:3: 1 repeated timestamps" in caplog.text


def test_missing_and_empty_files(tmp_path: Path) -> None:
    with pytest.raises(TrajectoryFileError, match="file not found"):
        read_tum(tmp_path / "none.txt")
    (tmp_path / "empty.txt").write_text("# only a comment\n")
    with pytest.raises(TrajectoryFileError, match="no data lines"):
        read_tum(tmp_path / "empty.txt")


def test_kitti_poses_and_times(tmp_path: Path) -> None:
    poses = tmp_path / "poses.txt"
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1 0 1 0 0 0 0 1 2\n")
    (tmp_path / "times.txt").write_text("0.0\n0.1\n")
    trajectory = read_kitti_poses(poses, read_times(tmp_path / "times.txt"))
    np.testing.assert_allclose(trajectory.positions_xyz[1], [1, 0, 2])
    np.testing.assert_allclose(trajectory.timestamps, [0.0, 0.1])
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 1 0 1 0 0 0 0 1 2\n")
    with pytest.raises(TrajectoryFileError, match=r"poses\.txt:2: rotation part is not orthonormal"):
        read_kitti_poses(poses)


@pytest.mark.shared
def test_reads_shared_trajectories(shared: Path) -> None:
    data = shared / "data" / "trajectories"
    kitti = read_kitti_poses(data / "KITTI_00_gt.txt", read_times(data / "KITTI_00_gt_times.txt"))
    assert kitti.num_poses == 4541
    desk = read_tum(data / "fr2_desk_groundtruth.txt")
    assert desk.num_poses == 20957 - 1  # one repeated timestamp (line 10863) keeps its first pose
    assert desk.timestamps[-1] - desk.timestamps[0] == pytest.approx(99, abs=1)
