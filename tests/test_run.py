"""``symbio run`` and the ``replay`` frontend: outputs, ATE with Sim(3) alignment, lost frames, failures."""

from __future__ import annotations

import json
import math
import shutil
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from evo.core.trajectory import PoseTrajectory3D
from scipy.spatial.transform import Rotation

from eval.cli import main as symbio_main
from eval.run import KEYFRAMES_FILE, METRICS_FILE, TRAJECTORY_FILE, run_odometry
from frontends.base import TrackResult
from frontends.datasets import open_dataset
from frontends.replay import create as create_replay
from frontends.trajectory_io import read_tum, write_trajectory
from frontends.types import Frame, Keyframe
from slam_backend import Slam


def run_replay(dataset: Path, trajectory: Path, out: Path, *extra: str) -> dict[str, Any]:
    argv = ["run", str(dataset), "--frontend", "replay", "--set", f"trajectory={trajectory}", *extra]
    assert symbio_main([*argv, "--no-loops", "--no-progress", "--out", str(out)]) == 0
    metrics: dict[str, Any] = json.loads((out / METRICS_FILE).read_text())
    return metrics


def gt_lines(scene: Path) -> list[str]:
    return (scene / "groundtruth.txt").read_text().splitlines()


# --- replay of a TUM trajectory on the synthetic scene ------------------------------------------------


def test_replaying_the_ground_truth_gives_zero_ate(small_loop_scene: Path, tmp_path: Path) -> None:
    gt_file = small_loop_scene / "groundtruth.txt"
    json_copy = tmp_path / "figures.json"
    metrics = run_replay(small_loop_scene, gt_file, tmp_path / "out", "--json", str(json_copy))
    assert metrics["ate_rmse_before"] < 1e-6
    assert metrics["path_length"] == pytest.approx(read_tum(gt_file).path_length, rel=1e-9)
    assert metrics["frames"] == metrics["frames_tracked"] == metrics["ate_frames"] == 600
    assert metrics["tracking_lost"] == metrics["frontend_failures"] == 0
    assert metrics["segments"] == 1 and metrics["ate_segment"] == 0
    assert metrics["keyframes"] == 100  # 30 Hz, a keyframe every 0.2 s
    assert metrics["fps"] > 0 and metrics["interrupted"] is False and metrics["loop_closing"] is False
    assert json.loads(json_copy.read_text()) == metrics
    trajectory = read_tum(tmp_path / "out" / TRAJECTORY_FILE)
    np.testing.assert_allclose(trajectory.positions_xyz, read_tum(gt_file).positions_xyz, atol=1e-12)
    keyframes = read_tum(tmp_path / "out" / KEYFRAMES_FILE)
    assert keyframes.num_poses == 100
    np.testing.assert_allclose(np.diff(keyframes.timestamps), 0.2, atol=0.002)


@pytest.mark.slow
def test_ate_is_measured_after_sim3_alignment(small_loop_scene: Path, tmp_path: Path) -> None:
    gt = read_tum(small_loop_scene / "groundtruth.txt")
    moved = PoseTrajectory3D(poses_se3=gt.poses_se3, timestamps=gt.timestamps)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    transform = np.eye(4)
    transform[:3, :3] = Rotation.from_rotvec(math.radians(70) * axis).as_matrix()
    transform[:3, 3] = [4.0, -2.0, 7.5]
    moved.transform(transform)
    moved.scale(0.37)  # a monocular map: arbitrary scale and frame
    trajectory = tmp_path / "vo.txt"
    write_trajectory(trajectory, moved)
    assert np.abs(moved.positions_xyz - gt.positions_xyz).max() > 1.0
    metrics = run_replay(small_loop_scene, trajectory, tmp_path / "out")
    assert metrics["ate_rmse_before"] < 1e-6


@pytest.mark.slow
def test_frames_without_a_pose_are_lost_not_interpolated(
    small_loop_scene: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    lines = gt_lines(small_loop_scene)
    data = [i for i, line in enumerate(lines) if line and not line.startswith("#")]
    gap = set(data[100:150])  # frames 100-149 (GT has one pose per frame)
    trajectory = tmp_path / "gappy.txt"
    trajectory.write_text("\n".join(line for i, line in enumerate(lines) if i not in gap) + "\n")
    metrics = run_replay(small_loop_scene, trajectory, tmp_path / "out")
    assert metrics["tracking_lost"] == 50
    assert metrics["frames_tracked"] == metrics["ate_frames"] == 550
    assert metrics["ate_rmse_before"] < 1e-6
    assert "no pose for frame 100" in caplog.text
    written = read_tum(tmp_path / "out" / TRAJECTORY_FILE)
    stamps = open_dataset(small_loop_scene).timestamps
    assert not np.isin(stamps[100:150], written.timestamps).any()
    keyframes = read_tum(tmp_path / "out" / KEYFRAMES_FILE).timestamps
    assert not ((keyframes >= stamps[100]) & (keyframes <= stamps[149])).any()


@pytest.mark.slow
def test_keyframes_by_distance(small_loop_scene: Path, tmp_path: Path) -> None:
    gt_file = small_loop_scene / "groundtruth.txt"
    out = tmp_path / "out"
    metrics = run_replay(small_loop_scene, gt_file, out, "--set", "keyframe_distance=1.0")
    centres = read_tum(out / KEYFRAMES_FILE).positions_xyz
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    assert steps.min() >= 1.0 and steps.max() < 1.1  # 0.7 m/s at 30 Hz: 2.3 cm per frame
    assert metrics["keyframes"] == pytest.approx(metrics["path_length"], abs=2)


def test_malformed_trajectory_names_file_and_line(
    small_loop_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    lines = gt_lines(small_loop_scene)
    lines[6] = "1.2 0 0 x 0 0 0 1"
    trajectory = tmp_path / "bad.txt"
    trajectory.write_text("\n".join(lines) + "\n")
    argv = ["run", str(small_loop_scene), "--frontend", "replay", "--set", f"trajectory={trajectory}"]
    assert symbio_main([*argv, "--no-loops", "--out", str(tmp_path / "out")]) == 2
    assert f"{trajectory}:7: not a number: 'x'" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ([], "no trajectory file"),
        (["trajectory=t.txt", "format=g2o"], "must be one of"),
        (["trajectory=t.txt", "keyframe_distance=0"], "keyframe_distance must be positive"),
        (["trajectory=t.txt", "orb.nfeatures=0"], "nfeatures"),
    ],
)
def test_replay_config_errors(
    small_loop_scene: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    overrides: list[str],
    message: str,
) -> None:
    argv = ["run", str(small_loop_scene), "--frontend", "replay", "--out", str(tmp_path / "out")]
    assert symbio_main([*argv, *(f"--set={o}" for o in overrides)]) == 2
    assert message in capsys.readouterr().err


# --- run_odometry with misbehaving frontends ------------------------------------------------------------


class FailingFrontend:
    """Replays the GT but raises ``error`` on the frames whose index is in ``failing``."""

    name = "failing"

    def __init__(self, scene: Path, failing: set[int], error: type[BaseException]) -> None:
        self.inner = create_replay(open_dataset(scene).camera, [f"trajectory={scene / 'groundtruth.txt'}"])
        self.failing = failing
        self.error = error

    def track(self, frame: Frame) -> TrackResult:
        if frame.index in self.failing:
            raise self.error(f"boom on {frame.index}")
        return self.inner.track(frame)

    def keyframes(self) -> list[Keyframe]:
        return self.inner.keyframes()


@pytest.mark.slow
def test_a_frontend_that_raises_loses_only_those_frames(
    small_loop_scene: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    failing = {7, 8, 300, 599}
    dataset = open_dataset(small_loop_scene)
    frontend = FailingFrontend(small_loop_scene, failing, RuntimeError)
    metrics = run_odometry(
        dataset, Slam(dataset.camera, frontend=frontend, loop_detector=None), tmp_path, progress=False
    )
    assert metrics["frames"] == 600 and metrics["frames_tracked"] == 596
    assert metrics["tracking_lost"] == metrics["frontend_failures"] == 4
    assert metrics["ate_rmse_before"] < 1e-6
    assert f"frontend failing failed on {dataset.entries[300].path}" in caplog.text
    assert read_tum(tmp_path / TRAJECTORY_FILE).num_poses == 596


def test_an_interrupted_run_writes_what_it_has(small_loop_scene: Path, tmp_path: Path) -> None:
    dataset = open_dataset(small_loop_scene)
    frontend = FailingFrontend(small_loop_scene, {40}, KeyboardInterrupt)
    with pytest.raises(KeyboardInterrupt):
        run_odometry(
            dataset, Slam(dataset.camera, frontend=frontend, loop_detector=None), tmp_path, progress=False
        )
    metrics = json.loads((tmp_path / METRICS_FILE).read_text())
    assert metrics["interrupted"] is True
    assert metrics["frames"] == metrics["frames_tracked"] == 40
    assert metrics["keyframes"] == 7  # frames 0, 6, ..., 36
    assert metrics["ate_rmse_before"] < 1e-6
    assert read_tum(tmp_path / TRAJECTORY_FILE).num_poses == 40
    assert read_tum(tmp_path / KEYFRAMES_FILE).num_poses == 7


# --- KITTI layout ---------------------------------------------------------------------------------------

KITTI_FRAMES = 12
FEATURELESS_FRAME = 2


def kitti_poses(n: int) -> np.ndarray:
    """Camera-to-world poses driving forward (+z) while turning slowly about y."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        c, s = math.cos(0.05 * k), math.sin(0.05 * k)
        poses[k, :3, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        poses[k, :3, 3] = [0.1 * k, 0.02 * k * k, 1.2 * k]
    return poses


def write_kitti_poses(path: Path, poses: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(" ".join(f"{v:.12e}" for v in p[:3].ravel()) + "\n" for p in poses))


@pytest.fixture
def kitti_sequence(tmp_path: Path) -> Path:
    """``dataset/sequences/00/{image_0,times.txt,calib.txt}`` and ``dataset/poses/00.txt``; textured
    160x120 images except one flat grey frame."""
    root = tmp_path / "dataset" / "sequences" / "00"
    (root / "image_0").mkdir(parents=True)
    rng = np.random.default_rng(5)
    for k in range(KITTI_FRAMES):
        image = cv2.GaussianBlur(rng.integers(0, 256, (120, 160), dtype=np.uint8), (3, 3), 0)
        if k == FEATURELESS_FRAME:
            image[:] = 128
        assert cv2.imwrite(str(root / "image_0" / f"{k:06d}.png"), image)
    projection = " ".join(f"{v:.6e}" for v in (100.0, 0, 79.5, 0, 0, 100.0, 59.5, 0, 0, 0, 1, 0))
    (root / "calib.txt").write_text(f"P0: {projection}\nP1: {projection}\n")
    (root / "times.txt").write_text("".join(f"{0.1036 * k:.6e}\n" for k in range(KITTI_FRAMES)))
    write_kitti_poses(tmp_path / "dataset" / "poses" / "00.txt", kitti_poses(KITTI_FRAMES))
    return root


def test_replay_kitti_poses(kitti_sequence: Path, tmp_path: Path) -> None:
    poses_file = kitti_sequence.parent.parent / "poses" / "00.txt"
    out = tmp_path / "out"
    metrics = run_replay(kitti_sequence, poses_file, out, "--format", "kitti", "--set", "format=kitti")
    assert metrics["format"] == "kitti"
    assert metrics["frames_tracked"] == KITTI_FRAMES and metrics["tracking_lost"] == 0
    assert metrics["ate_rmse_before"] < 1e-6
    centres = kitti_poses(KITTI_FRAMES)[:, :3, 3]
    assert metrics["path_length"] == pytest.approx(np.linalg.norm(np.diff(centres, axis=0), axis=1).sum())
    # Every 0.2 s (2 frames at 0.1036 s); the flat frame 2 is passed over and frame 3 taken instead.
    keyframes = read_tum(out / KEYFRAMES_FILE)
    np.testing.assert_allclose(keyframes.timestamps / 0.1036, [0, 3, 5, 7, 9, 11])
    np.testing.assert_allclose(read_tum(out / TRAJECTORY_FILE).positions_xyz, centres, atol=1e-9)


def test_kitti_poses_shorter_than_the_sequence(kitti_sequence: Path, tmp_path: Path) -> None:
    short = tmp_path / "short.txt"
    write_kitti_poses(short, kitti_poses(KITTI_FRAMES)[:8])
    metrics = run_replay(kitti_sequence, short, tmp_path / "out", "--set", "format=kitti")
    assert metrics["frames_tracked"] == 8 and metrics["tracking_lost"] == 4
    assert metrics["ate_rmse_before"] < 1e-6


# --- the real frontend ------------------------------------------------------------------------------------


def test_a_run_that_never_initialises_says_so(
    small_loop_scene: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Two frames 1/30 s apart cannot initialise a monocular map: the user is told why nothing was
    posed instead of finding an empty trajectory."""
    pytest.importorskip("frontends.mono_vo")
    argv = ["run", str(small_loop_scene), "--frontend", "mono-vo", "--max-frames", "2", "--no-loops"]
    assert symbio_main([*argv, "--no-progress", "--out", str(tmp_path / "out")]) == 0
    assert "mono-vo posed none of the 2 frames: it never initialised" in caplog.text
    assert "too much motion between frames" in caplog.text


@pytest.mark.slow
def test_mono_vo_smoke(small_loop_scene: Path, tmp_path: Path) -> None:
    pytest.importorskip("frontends.mono_vo")
    out = tmp_path / "out"
    argv = ["run", str(small_loop_scene), "--frontend", "mono-vo", "--max-frames", "120"]
    assert symbio_main([*argv, "--no-loops", "--no-progress", "--out", str(out)]) == 0
    metrics = json.loads((out / METRICS_FILE).read_text())
    assert metrics["frames"] == 120 and metrics["frontend"] == "mono-vo"
    assert metrics["frames_tracked"] + metrics["tracking_lost"] <= 120
    for name in (TRAJECTORY_FILE, KEYFRAMES_FILE):
        assert (out / name).is_file()


@pytest.mark.parametrize("prefetching", [False, True])
def test_an_interrupted_run_counts_no_skip_the_reader_met_ahead_of_it(
    small_loop_scene: Path, tmp_path: Path, prefetching: bool
) -> None:
    """Frames decode ahead of tracking (frontends.datasets.base.ReadAhead), and a prefetching
    frontend hears of frames a few ahead of their turn (frontends.base.with_lookahead): broken
    frames met after the last frame tracked are not the run's skips."""
    scene = tmp_path / "scene"
    shutil.copytree(small_loop_scene, scene)
    dataset = open_dataset(scene)
    for index in (42, 43):
        dataset.entries[index].path.write_bytes(b"not an image")

    class SlowFailingFrontend(FailingFrontend):
        def track(self, frame: Frame) -> TrackResult:
            if frame.index == 40:
                time.sleep(1.0)  # the reader meanwhile fills its queue: 41, then 44 past the broken two
            return super().track(frame)

    class PrefetchingFailingFrontend(SlowFailingFrontend):
        def prefetch(self, frame: Frame) -> None:
            pass  # with_lookahead now reads frames 41-45 (42, 43 skipped) before 40 is tracked

    kind = PrefetchingFailingFrontend if prefetching else SlowFailingFrontend
    frontend = kind(scene, {40}, KeyboardInterrupt)
    with pytest.raises(KeyboardInterrupt):
        run_odometry(
            dataset,
            Slam(dataset.camera, frontend=frontend, loop_detector=None),
            tmp_path / "run",
            progress=False,
        )
    metrics = json.loads((tmp_path / "run" / METRICS_FILE).read_text())
    assert metrics["frames"] == 40 and metrics["frames_skipped"] == 0
