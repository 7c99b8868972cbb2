"""Dataset readers on tiny fixtures built in each exact on-disk layout, plus the shared clips."""

from __future__ import annotations

import math
import pickle
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest

from frontends.datasets import detect_format, open_dataset
from frontends.datasets.calib import write_intrinsics
from frontends.datasets.folder import VideoDataset
from frontends.datasets.tum import FREIBURG_INTRINSICS
from frontends.errors import CalibrationError, DatasetError, InputFileError, TrajectoryFileError
from frontends.types import CameraIntrinsics

W, H = 64, 48
CAMERA = CameraIntrinsics(50.0, 51.0, 32.0, 24.0, W, H, (0.1, -0.05, 0.001, 0.002))
EUROC_T0_NS = 1403636579763555584


# --- fixture builders ---------------------------------------------------------------------------------


def write_image(path: Path, seed: int = 0, size: tuple[int, int] = (W, H)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    image = np.random.default_rng(seed).integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)
    assert cv2.imwrite(str(path), image)


def write_images(folder: Path, names: list[str]) -> list[Path]:
    paths = [folder / name for name in names]
    for seed, path in enumerate(paths):
        write_image(path, seed)
    return paths


def kitti_poses(n: int) -> np.ndarray:
    """Camera-to-world poses driving forward (+z) while turning slowly about y."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    for k in range(n):
        c, s = math.cos(0.05 * k), math.sin(0.05 * k)
        poses[k, :3, :3] = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        poses[k, :3, 3] = [0.1 * k, 0.0, 1.2 * k]
    return poses


def write_kitti_poses(path: Path, poses: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(" ".join(f"{v:.9e}" for v in p[:3].ravel()) + "\n" for p in poses))


def projection(fx: float, cx: float, cy: float, tx: float = 0.0) -> str:
    return " ".join(f"{v:.6e}" for v in (fx, 0, cx, tx, 0, fx, cy, 0, 0, 0, 1, 0))


def make_kitti_clip(root: Path, n: int = 5) -> np.ndarray:
    """Like the shared kitti06 clip: image_l/, bare calib.txt without trailing newline, poses.txt."""
    write_images(root / "image_l", [f"{k:06d}.png" for k in range(n)])
    (root / "calib.txt").write_text(projection(40.5, 31.5, 23.5) + "\n" + projection(40.5, 31.5, 23.5, -20.0))
    poses = kitti_poses(n)
    write_kitti_poses(root / "poses.txt", poses)
    return poses


def make_kitti_official(dataset: Path, sequence: str, n: int = 4, with_poses: bool = True) -> Path:
    """``dataset/sequences/NN/{image_0,image_2,times.txt,calib.txt}`` and ``dataset/poses/NN.txt``."""
    root = dataset / "sequences" / sequence
    write_images(root / "image_0", [f"{k:06d}.png" for k in range(n)])
    write_images(root / "image_2", [f"{k:06d}.png" for k in range(n)])
    lines = [
        f"P0: {projection(40.0, 30.0, 20.0)}",
        f"P1: {projection(40.0, 30.0, 20.0, -20.0)}",
        f"P2: {projection(42.0, 31.0, 22.0, 2.0)}",
        f"P3: {projection(42.0, 31.0, 22.0, -18.0)}",
        f"Tr: {projection(1.0, 0.0, 0.0)}",
    ]
    (root / "calib.txt").write_text("\n".join(lines) + "\n")
    (root / "times.txt").write_text("".join(f"{0.1036 * k:.6e}\n" for k in range(n)))
    if with_poses:
        write_kitti_poses(dataset / "poses" / f"{sequence}.txt", kitti_poses(n))
    return root


SENSOR_YAML = """\
# General sensor definitions.
sensor_type: camera
comment: VI-Sensor cam0 (MT9M034)

# Sensor extrinsics wrt. the body-frame.
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.1,
         0.0, 0.0, -1.0, -0.2,
         0.0, 1.0, 0.0, 0.05,
         0.0, 0.0, 0.0, 1.0]

# Camera specific definitions.
rate_hz: 20
resolution: [64, 48]
camera_model: pinhole
intrinsics: [45.8654, 45.7296, 36.7215, 24.8375] #fu, fv, cu, cv
distortion_model: radial-tangential
distortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05]
"""


def euroc_gt_row(j: int) -> str:
    """GT sample j (200 Hz, 1 ms after the image clock): body at (1 + 0.01 j, 2, 3), yawed 90 deg about z."""
    stamp = EUROC_T0_NS + j * 5_000_000 + 1_000_000
    w = z = math.sqrt(0.5)
    values = [1 + 0.01 * j, 2.0, 3.0, w, 0.0, 0.0, z] + [0.0] * 9
    return ",".join([str(stamp)] + [f"{v:.9f}" for v in values])  # EuRoC: no spaces after commas


def make_euroc(root: Path, n: int = 4, first_gt: int = 5) -> Path:
    cam0 = root / "mav0" / "cam0"
    stamps = [EUROC_T0_NS + k * 50_000_000 for k in range(n)]
    write_images(cam0 / "data", [f"{s}.png" for s in stamps])
    (cam0 / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(f"{s},{s}.png\n" for s in stamps))
    (cam0 / "sensor.yaml").write_text(SENSOR_YAML)
    gt = root / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    gt.parent.mkdir(parents=True)
    header = "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], ...\n"
    gt.write_text(header + "".join(euroc_gt_row(j) + "\n" for j in range(first_gt, 10 * n)))
    return root


def make_tum(root: Path, n: int = 5) -> None:
    names = [f"{1305031102.175304 + 0.033 * k:.6f}.png" for k in range(n)]
    write_images(root / "rgb", names)
    (root / "rgb.txt").write_text(
        "# color images\n# file: 'x.bag'\n# timestamp filename\n"
        + "".join(f"{name[:-4]} rgb/{name}\n" for name in names)
    )


def make_loops(root: Path, n: int = 6) -> None:
    write_images(root / "images", [f"{k:06d}.jpg" for k in range(n)])
    (root / "gt_loop_pairs.txt").write_text("# query ref\n4 0\n5 1\n")


def make_video(path: Path, frames: int = 6, fps: float = 15.0) -> list[np.ndarray]:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), fps, (W, H))
    images = []
    for k in range(frames):
        image = np.full((H, W, 3), 20 * k, dtype=np.uint8)
        cv2.putText(image, str(k), (20, 35), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (255, 255, 255), 2)
        writer.write(image)
        images.append(image)
    writer.release()
    return images


def corrupt(path: Path) -> None:
    path.write_bytes(b"this is not a PNG file")


# --- KITTI --------------------------------------------------------------------------------------------


def test_kitti_clip_layout(tmp_path: Path) -> None:
    poses = make_kitti_clip(tmp_path)
    dataset = open_dataset(tmp_path)
    assert dataset.format_name == "kitti"
    assert len(dataset) == 5
    np.testing.assert_allclose(dataset.timestamps, np.arange(5) / 10)
    camera = dataset.camera
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (40.5, 40.5, 31.5, 23.5)
    assert (camera.width, camera.height) == (W, H)
    assert camera.distortion == ()
    assert dataset.gt_poses is not None
    np.testing.assert_allclose(dataset.gt_poses, poses, atol=1e-8)
    frames = list(dataset)
    assert [f.index for f in frames] == list(range(5))
    assert frames[3].gt_pose is not None
    np.testing.assert_allclose(frames[3].gt_pose, poses[3], atol=1e-8)
    assert frames[0].image.shape == (H, W, 3)


def test_kitti_official_layout(tmp_path: Path) -> None:
    root = make_kitti_official(tmp_path / "dataset", "03")
    dataset = open_dataset(root)
    assert dataset.format_name == "kitti"
    assert Path(dataset.entries[0].path).parent.name == "image_0"
    assert (dataset.camera.fx, dataset.camera.cx, dataset.camera.cy) == (40.0, 30.0, 20.0)
    np.testing.assert_allclose(dataset.timestamps, 0.1036 * np.arange(4))
    assert dataset.has_groundtruth


def test_kitti_colour_images_use_p2(tmp_path: Path) -> None:
    root = make_kitti_official(tmp_path / "dataset", "04")
    for path in (root / "image_0").iterdir():
        path.unlink()
    (root / "image_0").rmdir()
    dataset = open_dataset(root, "kitti")
    assert Path(dataset.entries[0].path).parent.name == "image_2"
    assert (dataset.camera.fx, dataset.camera.cx, dataset.camera.cy) == (42.0, 31.0, 22.0)


def test_kitti_sequence_without_published_poses(tmp_path: Path) -> None:
    dataset = open_dataset(make_kitti_official(tmp_path / "dataset", "11", with_poses=False))
    assert dataset.gt_poses is None and not dataset.has_groundtruth
    assert any("no ground truth" in note for note in dataset.notes)


def test_kitti_dataset_root_is_rejected_with_a_hint(tmp_path: Path) -> None:
    make_kitti_official(tmp_path / "dataset", "00")
    with pytest.raises(DatasetError, match="sequences/00"):
        open_dataset(tmp_path / "dataset")


def test_kitti_calib_override(tmp_path: Path) -> None:
    make_kitti_clip(tmp_path / "clip")
    write_intrinsics(tmp_path / "cam.yaml", CAMERA)
    dataset = open_dataset(tmp_path / "clip", calib=tmp_path / "cam.yaml")
    assert dataset.camera.fx == 50.0 and dataset.camera.distortion == CAMERA.distortion


@pytest.mark.parametrize(
    ("edit", "error", "location"),
    [
        (
            lambda r: (r / "poses.txt").write_text(
                (r / "poses.txt").read_text() + "1 0 0 0 0 1 0 0 0 0 1 0\n"
            ),
            DatasetError,
            "poses.txt: 6 poses",
        ),
        (lambda r: (r / "times.txt").write_text("0.0\n0.1\n0.2\n"), DatasetError, "times.txt: 3 timestamps"),
        (lambda r: (r / "times.txt").write_text("0.0\n0.1\n0.1\n0.3\n0.4\n"), DatasetError, "times.txt:3"),
        (
            lambda r: (r / "poses.txt").write_text(
                "\n".join([*(r / "poses.txt").read_text().splitlines()[:2], "1 0 0 0 0 1 0 0 0 0 1"])
            ),
            TrajectoryFileError,
            "poses.txt:3",
        ),
        (
            lambda r: (r / "calib.txt").write_text(projection(1, 2, 3) + "\n1 2 x 4 5 6 7 8 9 10 11 12\n"),
            CalibrationError,
            "calib.txt:2",
        ),
        (lambda r: (r / "calib.txt").write_text(f"P1: {projection(1, 2, 3)}\n"), CalibrationError, "no P0"),
        (lambda r: (r / "calib.txt").unlink(), CalibrationError, "calib.txt: not found"),
    ],
    ids=[
        "poses-count",
        "times-count",
        "times-duplicate",
        "poses-bad-line",
        "calib-bad-line",
        "calib-no-p0",
        "calib-missing",
    ],
)
def test_kitti_bad_input(
    tmp_path: Path, edit: Callable[[Path], object], error: type[Exception], location: str
) -> None:
    make_kitti_clip(tmp_path)
    edit(tmp_path)
    with pytest.raises(error) as exc:
        open_dataset(tmp_path, "kitti")
    assert location in str(exc.value)


def test_corrupt_image_is_skipped_and_counted(tmp_path: Path) -> None:
    make_kitti_clip(tmp_path)
    corrupt(tmp_path / "image_l" / "000002.png")
    dataset = open_dataset(tmp_path)
    frames = list(dataset)
    assert [f.index for f in frames] == [0, 1, 3, 4]
    assert len(dataset.skipped) == 1 and dataset.skipped[0].index == 2
    assert "000002.png" in dataset.skipped[0].reason
    with pytest.raises(DatasetError, match=r"000002\.png"):
        list(open_dataset(tmp_path, strict=True))


# --- EuRoC --------------------------------------------------------------------------------------------


def test_euroc_layout_and_camera_pose(tmp_path: Path) -> None:
    root = make_euroc(tmp_path / "MH_01_easy")
    for path in (root, root / "mav0"):
        dataset = open_dataset(path)
        assert dataset.format_name == "euroc"
        assert len(dataset) == 4
    np.testing.assert_allclose(dataset.timestamps - dataset.timestamps[0], [0.0, 0.05, 0.1, 0.15], atol=1e-6)
    assert dataset.timestamps[0] == pytest.approx(1403636579.763555584)
    camera = dataset.camera
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (45.8654, 45.7296, 36.7215, 24.8375)
    assert camera.distortion == (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    # T_WB of GT row 20 (nearest to frame 2): yaw 90 deg about z, at (1.2, 2, 3); T_BS: 90 deg about x,
    # at (0.1, -0.2, 0.05). T_WC = T_WB @ T_BS, multiplied out by hand:
    expected = np.array([[0, 0, 1, 1.4], [1, 0, 0, 2.1], [0, 1, 0, 3.05], [0, 0, 0, 1]], dtype=float)
    assert dataset.gt_poses is not None
    np.testing.assert_allclose(dataset.gt_poses[2], expected, atol=1e-9)
    # The GT starts 26 ms after frame 0: beyond the 10 ms tolerance.
    assert np.isnan(dataset.gt_poses[0]).all()
    assert any("1 frames have no ground truth" in note for note in dataset.notes)
    frames = list(dataset)
    assert frames[0].gt_pose is None and frames[1].gt_pose is not None


@pytest.mark.parametrize(
    ("edit", "error", "location"),
    [
        (
            lambda c: c.write_text(
                c.read_text().replace(f"{EUROC_T0_NS + 100_000_000},", f"{EUROC_T0_NS + 50_000_000},", 1)
            ),
            DatasetError,
            "cam0/data.csv:4: duplicate",
        ),
        (
            lambda c: c.write_text(c.read_text() + f"{EUROC_T0_NS},{EUROC_T0_NS}.png\n"),
            DatasetError,
            "cam0/data.csv:6: decreasing",
        ),
        (lambda c: c.write_text(c.read_text() + "12345\n"), DatasetError, "cam0/data.csv:6"),
        (lambda c: c.write_text(c.read_text() + "1.5e9,x.png\n"), DatasetError, "cam0/data.csv:6"),
        (lambda c: (c.parent / "sensor.yaml").unlink(), CalibrationError, "sensor.yaml: not found"),
    ],
    ids=["duplicate", "decreasing", "one-field", "float-stamp", "no-sensor-yaml"],
)
def test_euroc_bad_image_list(
    tmp_path: Path, edit: Callable[[Path], object], error: type[Exception], location: str
) -> None:
    make_euroc(tmp_path)
    edit(tmp_path / "mav0" / "cam0" / "data.csv")
    with pytest.raises(error) as exc:
        open_dataset(tmp_path)
    assert location in str(exc.value)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda rows: rows[3].rsplit(",", 1)[0], r"groundtruth_estimate0/data\.csv:4: expected 8 or 17"),
        (lambda rows: rows[1], r"groundtruth_estimate0/data\.csv:4: decreasing"),
    ],
    ids=["16-columns", "decreasing"],
)
def test_euroc_bad_groundtruth_line(tmp_path: Path, edit: Callable[[list[str]], str], message: str) -> None:
    make_euroc(tmp_path)
    gt = tmp_path / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    rows = gt.read_text().splitlines()
    rows[3] = edit(rows)
    gt.write_text("\n".join(rows) + "\n")
    with pytest.raises(TrajectoryFileError, match=message):
        open_dataset(tmp_path)


def test_euroc_repeated_groundtruth_stamp_keeps_first_row(tmp_path: Path) -> None:
    make_euroc(tmp_path)
    gt = tmp_path / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    rows = gt.read_text().splitlines()
    stamp = rows[-1].split(",", 1)[0]
    gt.write_text("\n".join([*rows, f"{stamp},{euroc_gt_row(0).split(',', 1)[1]}"]) + "\n")
    assert open_dataset(tmp_path).has_groundtruth


def test_euroc_without_sensor_yaml_uses_calib_and_body_pose(tmp_path: Path) -> None:
    make_euroc(tmp_path)
    (tmp_path / "mav0" / "cam0" / "sensor.yaml").unlink()
    write_intrinsics(tmp_path / "cam.yaml", CAMERA)
    dataset = open_dataset(tmp_path, calib=tmp_path / "cam.yaml")
    assert dataset.camera.fx == 50.0
    assert dataset.gt_poses is not None
    np.testing.assert_allclose(dataset.gt_poses[2, :3, 3], [1.2, 2.0, 3.0])
    assert any("T_BS = identity" in note for note in dataset.notes)


# --- image folder and video ---------------------------------------------------------------------------


def test_image_folder_with_times_txt(tmp_path: Path) -> None:
    write_images(tmp_path, ["a.png", "b.png", "c.png"])
    write_intrinsics(tmp_path / "intrinsics.yaml", CAMERA)
    (tmp_path / "times.txt").write_text("0.5\n0.7\n0.9\n")
    dataset = open_dataset(tmp_path)
    assert dataset.format_name == "folder"
    np.testing.assert_allclose(dataset.timestamps, [0.5, 0.7, 0.9])
    assert dataset.camera.as_dict() == CAMERA.as_dict()
    assert dataset.camera.source == str(tmp_path / "intrinsics.yaml")
    assert dataset.gt_poses is None and len(list(dataset)) == 3


def test_image_folder_timestamps_from_names_are_time_ordered(tmp_path: Path) -> None:
    write_images(tmp_path, ["10.25.png", "9.5.png", "9.75.png"])
    write_intrinsics(tmp_path / "cam.yaml", CAMERA)
    dataset = open_dataset(tmp_path, calib=tmp_path / "cam.yaml")
    np.testing.assert_allclose(dataset.timestamps, [9.5, 9.75, 10.25])
    assert [e.path.name for e in dataset.entries] == ["9.5.png", "9.75.png", "10.25.png"]


def test_image_folder_frame_numbers_are_not_seconds(tmp_path: Path) -> None:
    write_images(tmp_path, ["000000.png", "000001.png", "000002.png"])
    write_intrinsics(tmp_path / "intrinsics.yaml", CAMERA)
    dataset = open_dataset(tmp_path)
    np.testing.assert_allclose(dataset.timestamps, np.arange(3) / 30)
    assert any("1/30 s apart" in note for note in dataset.notes)


@pytest.mark.parametrize(
    ("camera", "times", "error", "message"),
    [
        (None, None, CalibrationError, "pass --calib"),
        (CAMERA.with_size(128, 96), None, CalibrationError, "calibration is for 128x96 images"),
        (CAMERA, "1\n2\n", DatasetError, "times.txt: 2 timestamps but 3 images"),
        (CAMERA, "1\n3\n2\n", DatasetError, "times.txt:3: decreasing"),
    ],
    ids=["no-intrinsics", "wrong-size", "times-count", "times-decreasing"],
)
def test_image_folder_bad_input(
    tmp_path: Path, camera: CameraIntrinsics | None, times: str | None, error: type[Exception], message: str
) -> None:
    write_images(tmp_path, ["a.png", "b.png", "c.png"])
    if camera is not None:
        write_intrinsics(tmp_path / "intrinsics.yaml", camera)
    if times is not None:
        (tmp_path / "times.txt").write_text(times)
    with pytest.raises(error, match=message):
        open_dataset(tmp_path, "folder")


def test_video(tmp_path: Path) -> None:
    images = make_video(tmp_path / "walk.avi")
    write_intrinsics(tmp_path / "walk.yaml", CAMERA)
    dataset = open_dataset(tmp_path / "walk.avi")
    assert dataset.format_name == "video"
    assert len(dataset) == 6
    np.testing.assert_allclose(dataset.timestamps, np.arange(6) / 15)
    frames = list(dataset)
    assert [f.index for f in frames] == list(range(6)) and not dataset.skipped
    assert frames[0].image.shape == (H, W, 3)
    # MJPG is lossy: compare loosely, against the frame written and the frame read by iteration.
    seeked = dataset.read_image(3)
    assert seeked is not None
    assert np.abs(seeked.astype(int) - images[3]).mean() < 8
    assert np.abs(seeked.astype(int) - frames[3].image).mean() < 1


def test_video_shorter_than_announced(tmp_path: Path) -> None:
    make_video(tmp_path / "v.avi")
    write_intrinsics(tmp_path / "intrinsics.yaml", CAMERA)
    opened = open_dataset(tmp_path / "v.avi")
    # The container announces 8 frames but holds 6.
    longer = [*opened.entries, *(type(opened.entries[0])(k / 15, opened.root) for k in (6, 7))]
    dataset = VideoDataset(opened.root, opened.camera, longer)
    assert len(list(dataset)) == 6
    assert [s.index for s in dataset.skipped] == [6, 7]
    with pytest.raises(DatasetError, match="ended after 6 of 8"):
        list(VideoDataset(opened.root, opened.camera, longer, strict=True))


def test_video_errors(tmp_path: Path) -> None:
    make_video(tmp_path / "v.avi")
    with pytest.raises(CalibrationError, match="pass --calib"):
        open_dataset(tmp_path / "v.avi")
    (tmp_path / "bad.mp4").write_bytes(b"\x00" * 1000)
    write_intrinsics(tmp_path / "intrinsics.yaml", CAMERA)
    with pytest.raises(DatasetError, match=r"bad\.mp4"):
        open_dataset(tmp_path / "bad.mp4")


# --- loop-pairs sets ----------------------------------------------------------------------------------


def test_loop_pairs_layout(tmp_path: Path) -> None:
    make_loops(tmp_path)
    dataset = open_dataset(tmp_path)
    assert dataset.format_name == "loops"
    assert len(dataset) == 6
    np.testing.assert_allclose(dataset.timestamps, np.arange(6.0))
    assert dataset.camera.fx == pytest.approx(W / (2 * math.tan(math.radians(30))))
    assert (dataset.camera.cx, dataset.camera.cy) == (W / 2, H / 2)
    assert dataset.camera.source.startswith("estimated")
    pairs, source = dataset.loop_pairs()
    assert source == "file" and pairs is not None
    assert pairs.tolist() == [[4, 0], [5, 1]]
    assert not dataset.has_groundtruth


def test_loop_pairs_intrinsics_file_and_bad_index(tmp_path: Path) -> None:
    make_loops(tmp_path)
    write_intrinsics(tmp_path / "intrinsics.yaml", CAMERA)
    assert open_dataset(tmp_path).camera.fx == 50.0
    (tmp_path / "gt_loop_pairs.txt").write_text("# query ref\n4 0\n6 1\n")
    with pytest.raises(DatasetError) as exc:
        open_dataset(tmp_path)
    assert "gt_loop_pairs.txt:3" in str(exc.value)


# --- TUM ----------------------------------------------------------------------------------------------


def test_tum_groundtruth_association_and_freiburg_intrinsics(tmp_path: Path) -> None:
    root = tmp_path / "rgbd_dataset_freiburg2_desk"
    make_tum(root)
    dataset = open_dataset(root)
    stamps = dataset.timestamps
    # GT 10 ms after frames 0-3 (associated), 30 ms after frame 4 (beyond 0.02 s: no GT).
    offsets = [0.01, 0.01, 0.01, 0.01, 0.03]
    rows = [f"{t + o:.6f} {k} 0 0 0 0 0 1\n" for k, (t, o) in enumerate(zip(stamps, offsets, strict=True))]
    (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "".join(rows))
    dataset = open_dataset(root)
    assert dataset.format_name == "tum" and len(dataset) == 5
    assert dataset.gt_poses is not None
    np.testing.assert_allclose(dataset.gt_poses[:4, 0, 3], [0, 1, 2, 3])
    assert np.isnan(dataset.gt_poses[4]).all()
    fx, _, _, cy, dist = FREIBURG_INTRINSICS[2]
    assert dataset.camera.fx == pytest.approx(fx * W / 640)
    assert dataset.camera.cy == pytest.approx(cy * H / 480)
    assert dataset.camera.distortion == dist
    assert "freiburg2" in dataset.camera.source


def test_tum_intrinsics_yaml_override(tmp_path: Path) -> None:
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    make_tum(root)
    write_intrinsics(root / "intrinsics.yaml", CAMERA)
    assert open_dataset(root).camera.fx == 50.0


def test_tum_without_rgb_txt_uses_file_names(tmp_path: Path) -> None:
    make_tum(tmp_path)
    (tmp_path / "rgb.txt").unlink()
    dataset = open_dataset(tmp_path)
    assert dataset.format_name == "tum" and len(dataset) == 5
    assert dataset.timestamps[1] - dataset.timestamps[0] == pytest.approx(0.033)
    assert "ROS default" in dataset.camera.source


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("1305031102.3 rgb/x.png extra", "rgb.txt:5: expected"),
        ("abc rgb/x.png", "rgb.txt:5: timestamp"),
        ("1305031102.175304 rgb/x.png", "rgb.txt:5: duplicate"),
        ("1305031102.1 rgb/x.png", "rgb.txt:5: decreasing"),
    ],
    ids=["fields", "not-a-number", "duplicate", "decreasing"],
)
def test_tum_bad_rgb_txt_line(tmp_path: Path, line: str, message: str) -> None:
    make_tum(tmp_path)
    lines = (tmp_path / "rgb.txt").read_text().splitlines()
    lines.insert(4, line)  # the 5th line (after three comments and one image)
    (tmp_path / "rgb.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=message):
        open_dataset(tmp_path)


def test_tum_missing_listed_image_strict(tmp_path: Path) -> None:
    make_tum(tmp_path)
    next((tmp_path / "rgb").iterdir()).unlink()
    assert len(open_dataset(tmp_path)) == 5
    with pytest.raises(DatasetError, match="listed image not found"):
        open_dataset(tmp_path, strict=True)


# --- detection ----------------------------------------------------------------------------------------


def test_detection_picks_each_layout(tmp_path: Path) -> None:
    make_kitti_clip(tmp_path / "kitti")
    make_euroc(tmp_path / "euroc")
    make_tum(tmp_path / "tum")
    make_loops(tmp_path / "loops")
    write_images(tmp_path / "folder", ["a.png"])
    make_video(tmp_path / "clip.avi")
    expected = {
        "kitti": "kitti",
        "euroc": "euroc",
        "euroc/mav0": "euroc",
        "tum": "tum",
        "loops": "loops",
        "folder": "folder",
        "clip.avi": "video",
    }
    assert {name: detect_format(tmp_path / name) for name in expected} == expected
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="unrecognised dataset layout"):
        open_dataset(tmp_path / "empty")
    with pytest.raises(DatasetError, match="not found"):
        open_dataset(tmp_path / "nowhere")


# --- shared data --------------------------------------------------------------------------------------


@pytest.mark.shared
def test_shared_kitti_clip(shared: Path) -> None:
    dataset = open_dataset(shared / "data/clips/kitti06_f000-050", "kitti")
    assert len(dataset) == 51
    assert (dataset.camera.width, dataset.camera.height) == (1226, 370)
    assert dataset.camera.fx == pytest.approx(707.0912)
    assert dataset.has_groundtruth


@pytest.mark.shared
def test_shared_loop_pairs(shared: Path) -> None:
    dataset = open_dataset(shared / "data/loops/rtabmap_samples")
    assert dataset.format_name == "loops"
    assert len(dataset) == 84
    pairs, source = dataset.loop_pairs()
    assert source == "file" and pairs is not None and len(pairs) == 228


@pytest.mark.shared
def test_shared_tum_clip(shared: Path) -> None:
    dataset = open_dataset(shared / "data/clips/tum_fr3_long_office_17")
    assert dataset.format_name == "tum"
    assert len(dataset) == 17
    assert (dataset.camera.fx, dataset.camera.fy) == (535.4, 539.2)
    assert not dataset.has_groundtruth


@pytest.mark.parametrize("error_type", [InputFileError, DatasetError, TrajectoryFileError])
def test_input_errors_survive_pickling_across_worker_processes(error_type: type[InputFileError]) -> None:
    # The benchmarks run scenes in process pools; an error that cannot be rebuilt there surfaces as
    # "a process in the pool terminated abruptly" instead of the file and line.
    error = error_type("scene/gt_loop_pairs.txt", "frame index out of range 0..199: [407, 0]", line=2)
    copy = pickle.loads(pickle.dumps(error))
    assert type(copy) is error_type
    assert (copy.path, copy.line, copy.reason, str(copy)) == (error.path, 2, error.reason, str(error))
