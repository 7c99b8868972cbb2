"""Dataset inputs as a hostile or careless user makes them (issue 41): file names that are not UTF-8,
decompression-bomb images, symbolic link loops, calibrations that are not what they claim, and
random bytes as image files. Each is read, skipped and counted, or refused with an error naming the
file (and line) — never a crash, a traceback or gigabytes of memory.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import textwrap
import tracemalloc
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from eval.cli import main as symbio_main
from frontends.datasets import open_dataset
from frontends.datasets.base import SKIP_CAUSES, Dataset, decode_image
from frontends.datasets.calib import write_intrinsics
from frontends.errors import CalibrationError, DatasetError, SymbioError
from frontends.trajectory_io import read_times
from frontends.types import CameraIntrinsics

W, H = 64, 48
CAMERA = CameraIntrinsics(50.0, 51.0, 32.0, 24.0, W, H)
#: Bytes that are not UTF-8 in a name: Python keeps them as lone surrogates ("caf\udce9").
CAFE = os.fsdecode(b"caf\xe9")
BAD_NAME = os.fsdecode(b"im\xff")
#: HYPOTHESIS_PROFILE=fuzz (CONTRIBUTING) runs the long fuzz, as for tests/test_fuzz_parsers.py.
FUZZ_EXAMPLES = 10_000 if os.environ.get("HYPOTHESIS_PROFILE") == "fuzz" else 120


def noise(seed: int, size: tuple[int, int] = (W, H)) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)


def write_png(path: Path, seed: int) -> np.ndarray:
    """Write through bytes: cv2.imwrite has the same trouble with such names as cv2.imread."""
    image = noise(seed)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(cv2.imencode(".png", image)[1].tobytes())
    return image


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_with_header_size(width: int, height: int) -> bytes:
    """A W x H PNG whose IHDR (CRC fixed) declares another size: what a crafted header looks like."""
    data = bytearray(cv2.imencode(".png", noise(0))[1].tobytes())
    depth_colour_etc = bytes(data[24:29])  # IHDR: width, height, then these 5 bytes; CRC after
    data[8:33] = png_chunk(b"IHDR", struct.pack(">II", width, height) + depth_colour_etc)
    return bytes(data)


@pytest.fixture(scope="module")
def bomb_png(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """The hostile tester's file: a real 20000 x 20000 grey PNG of zeros, 389 KB (1.2 s to make)."""
    path = tmp_path_factory.mktemp("bomb") / "bomb.png"
    compressor = zlib.compressobj(9)
    row = bytes(20_000 + 1)  # filter byte + one row of grey pixels
    idat = b"".join([*(compressor.compress(row) for _ in range(20_000)), compressor.flush()])
    header = struct.pack(">IIBBBBB", 20_000, 20_000, 8, 0, 0, 0, 0)
    data = (
        b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", header) + png_chunk(b"IDAT", idat) + png_chunk(b"IEND", b"")
    )
    path.write_bytes(data)
    return data


# --- file and folder names that are not UTF-8 ---------------------------------------------------------


def make_folder(root: Path, n: int = 3, name: str = BAD_NAME) -> list[np.ndarray]:
    images = [write_png(root / f"{name}{k}.png", k) for k in range(n)]
    write_intrinsics(root / "intrinsics.yaml", CAMERA)
    return images


def make_tum(root: Path, n: int = 3, index: bool = True) -> list[np.ndarray]:
    stamps = [f"{1305031102.175304 + 0.033 * k:.6f}" for k in range(n)]
    images = [write_png(root / "rgb" / f"{s}.png", k) for k, s in enumerate(stamps)]
    if index:  # rgb.txt names the files with bytes that are not UTF-8, as the files on disk have
        for k, stamp in enumerate(stamps):
            (root / "rgb" / f"{stamp}.png").rename(root / "rgb" / f"{BAD_NAME}{k}.png")
        lines = b"".join(b"%s rgb/im\xff%d.png\n" % (s.encode(), k) for k, s in enumerate(stamps))
        (root / "rgb.txt").write_bytes(b"# timestamp filename\n" + lines)
    return images


def make_euroc(root: Path, n: int = 3) -> list[np.ndarray]:
    cam0 = root / "mav0" / "cam0"
    stamps = [1403636579763555584 + k * 50_000_000 for k in range(n)]
    images = [write_png(cam0 / "data" / f"{BAD_NAME}{k}.png", k) for k in range(n)]
    rows = b"".join(b"%d,im\xff%d.png\n" % (s, k) for k, s in enumerate(stamps))
    (cam0 / "data.csv").write_bytes(b"#timestamp [ns],filename\n" + rows)
    (cam0 / "sensor.yaml").write_text(f"resolution: [{W}, {H}]\nintrinsics: [50.0, 51.0, 32.0, 24.0]\n")
    return images


@pytest.mark.parametrize(
    ("make", "fmt"),
    [
        (make_folder, "folder"),
        (make_tum, "tum"),
        (lambda root: make_tum(root, index=False), "tum"),
        (make_euroc, "euroc"),
    ],
    ids=["folder", "tum-rgb-txt", "tum-file-names", "euroc"],
)
def test_names_that_are_not_utf8_are_read(
    tmp_path: Path, make: Callable[[Path], list[np.ndarray]], fmt: str
) -> None:
    root = tmp_path / CAFE
    images = make(root)
    dataset = open_dataset(root)
    assert dataset.format_name == fmt
    frames = list(dataset)
    assert not dataset.skipped
    assert len(frames) == len(images)
    for frame, image in zip(frames, images, strict=True):
        np.testing.assert_array_equal(frame.image, image)
        assert Path(frame.path or "").is_file()  # the name still opens the file it came from
    # What is shown of the dataset prints on any stream: the bytes as \xNN escapes.
    info = dataset.info()
    assert "caf\\xe9" in info["path"]
    info["path"].encode("utf-8")


def test_a_skipped_image_with_such_a_name_is_named_printably(tmp_path: Path) -> None:
    make_folder(tmp_path / CAFE)
    (tmp_path / CAFE / f"{BAD_NAME}1.png").write_bytes(b"not an image")
    dataset = open_dataset(tmp_path / CAFE)
    assert [frame.index for frame in dataset] == [0, 2]
    [skipped] = dataset.skipped
    assert skipped.cause == "undecodable image"
    assert "caf\\xe9/im\\xff1.png" in skipped.reason
    (skipped.where + skipped.reason).encode("utf-8")  # a log file or stdout takes it
    with pytest.raises(DatasetError) as error:
        list(open_dataset(tmp_path / CAFE, strict=True))
    str(error.value).encode("utf-8")


def test_the_cli_prints_such_names_on_a_strict_utf8_stdout(tmp_path: Path) -> None:
    """In a subprocess: the bug was a segfault inside cv2.imread, and stdout must not be lenient."""
    make_folder(tmp_path / CAFE)
    result = subprocess.run(
        [sys.executable, "-m", "eval.cli", "datasets", "info", "--check-images", str(tmp_path / CAFE)],
        capture_output=True,
        env={**os.environ, "PYTHONIOENCODING": "utf-8:strict"},
        timeout=120,
        check=False,
    )
    stdout = result.stdout.decode()
    assert result.returncode == 0, result.stderr.decode()[-2000:]
    assert "frames_decoded        3" in stdout and "caf\\xe9" in stdout


def test_a_video_whose_name_is_not_utf8_is_refused_clearly(tmp_path: Path) -> None:
    # cv2.VideoCapture crashes the process on such a name: write under a plain name, then rename.
    writer = cv2.VideoWriter(str(tmp_path / "v.avi"), cv2.VideoWriter.fourcc(*"MJPG"), 10.0, (W, H))
    for k in range(3):
        writer.write(noise(k))
    writer.release()
    video = tmp_path / f"{CAFE}.avi"
    (tmp_path / "v.avi").rename(video)
    write_intrinsics(tmp_path / "intrinsics.yaml", CAMERA)
    with pytest.raises(DatasetError, match="not UTF-8") as error:
        open_dataset(video)
    assert "caf\\xe9.avi" in str(error.value)


# --- images larger than they look ---------------------------------------------------------------------


def test_a_decompression_bomb_mid_sequence_is_skipped_without_decoding(
    tmp_path: Path, bomb_png: bytes
) -> None:
    """Peak memory measured in a fresh process (OpenCV's own buffers are invisible to tracemalloc)."""
    make_folder(tmp_path / "seq", n=4, name="im")
    (tmp_path / "seq" / "im1.png").write_bytes(bomb_png)
    probe = textwrap.dedent(
        """
        import resource, sys
        from frontends.datasets import open_dataset
        dataset = open_dataset(sys.argv[1])
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        frames = [frame.index for frame in dataset]
        grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before
        print(frames, [s.cause for s in dataset.skipped], grown * (1 if sys.platform == "darwin" else 1024))
        """
    )
    result = subprocess.run(
        [sys.executable, "-c", probe, str(tmp_path / "seq")], capture_output=True, timeout=120, check=False
    )
    assert result.returncode == 0, result.stderr.decode()[-2000:]
    frames_text, _, grown_text = result.stdout.decode().strip().rpartition(" ")
    assert frames_text == "[0, 2, 3] ['wrong image size']"
    assert int(grown_text) < 64 * 2**20  # decoding it took 400 MB (grey) to 1.2 GB (BGR)


def test_a_decompression_bomb_is_not_decoded_without_a_calibration(tmp_path: Path, bomb_png: bytes) -> None:
    (tmp_path / "seq").mkdir()
    (tmp_path / "seq" / "000000.png").write_bytes(bomb_png)
    write_png(tmp_path / "seq" / "000001.png", 1)
    write_intrinsics(tmp_path / "seq" / "intrinsics.yaml", CAMERA)
    tracemalloc.start()
    try:
        with pytest.raises(
            DatasetError,
            match=r"000000\.png: image is larger than 179 megapixels, more than the 100 megapixels",
        ):
            open_dataset(tmp_path / "seq")  # the first image would set every frame's size
        assert decode_image(tmp_path / "seq" / "000000.png") is None  # vocabulary training's reader
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 32 * 2**20


@pytest.mark.parametrize(
    ("declared", "found"),
    [((640, 480), "640x480"), ((30_000, 30_000), "larger than 179 megapixels")],
    ids=["vga", "beyond-pillow-limit"],
)
def test_a_header_declaring_another_size_is_skipped_as_wrong_size(
    tmp_path: Path, declared: tuple[int, int], found: str
) -> None:
    make_folder(tmp_path, n=3, name="im")
    (tmp_path / "im1.png").write_bytes(png_with_header_size(*declared))
    dataset = open_dataset(tmp_path)
    assert [frame.index for frame in dataset] == [0, 2]
    assert [(s.index, s.cause) for s in dataset.skipped] == [(1, "wrong image size")]
    assert f"image is {found}, the camera's calibration is for 64x48" in dataset.skipped[0].reason


def test_a_header_above_100_megapixels_is_refused_without_a_calibration(tmp_path: Path) -> None:
    make_folder(tmp_path, n=2, name="im")
    (tmp_path / "im0.png").write_bytes(png_with_header_size(12_000, 12_000))
    with pytest.raises(DatasetError, match=r"image is 12000x12000 \(144 megapixels\), more than the 100"):
        open_dataset(tmp_path)


def test_a_file_larger_than_its_image_needs_is_not_read(tmp_path: Path) -> None:
    make_folder(tmp_path, n=3, name="im")
    path = tmp_path / "im1.png"
    with path.open("ab") as handle:  # a valid 64x48 PNG followed by 17 MB
        handle.truncate(path.stat().st_size + (17 << 20))
    dataset = open_dataset(tmp_path)
    assert [frame.index for frame in dataset] == [0, 2]
    [skipped] = dataset.skipped
    assert skipped.cause == "undecodable image" and "bytes a 64x48 image needs" in skipped.reason


# --- symbolic link loops -------------------------------------------------------------------------------


def test_symlink_loops_are_clear_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    make_folder(tmp_path / "seq", name="im")
    (tmp_path / "a").symlink_to(tmp_path / "b")
    (tmp_path / "b").symlink_to(tmp_path / "a")
    with pytest.raises(DatasetError, match=r"/a: symbolic link loop"):
        open_dataset(tmp_path / "a")
    with pytest.raises(CalibrationError, match=r"/a: symbolic link loop"):
        open_dataset(tmp_path / "seq", calib=tmp_path / "a")
    with pytest.raises(CalibrationError, match=r"/seq: is a folder, not a file"):
        open_dataset(tmp_path / "seq", calib=tmp_path / "seq")
    # symbio run resolved both paths (for its checkpoint header) before opening them: a traceback.
    for argv in (
        ["run", str(tmp_path / "a"), "--out", str(tmp_path / "out")],
        ["run", str(tmp_path / "seq"), "--calib", str(tmp_path / "a"), "--out", str(tmp_path / "out")],
    ):
        with pytest.raises(SystemExit) as exited:
            symbio_main(argv)
        assert exited.value.code == 2
        assert f"{tmp_path / 'a'}: symbolic link loop" in capsys.readouterr().err


# --- calibrations that are not what they claim ---------------------------------------------------------

#: KITTI odometry sequence 00's calib.txt as published: P2 and P3 have a baseline in all three rows,
#: Tr (velodyne to camera) is no projection at all.
KITTI_CALIB = """\
P0: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 0.000000000000e+00 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P1: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.861448000000e+02 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P2: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 4.538225000000e+01 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 -1.130887000000e-01 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 3.779761000000e-03
P3: 7.188560000000e+02 0.000000000000e+00 6.071928000000e+02 -3.372877000000e+02 0.000000000000e+00 7.188560000000e+02 1.852157000000e+02 2.369057000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 4.915215000000e-03
Tr: 4.276802385584e-04 -9.999672484946e-01 -8.084491683471e-03 -1.198459927713e-02 -7.210626507497e-03 8.081198471645e-03 -9.999413164504e-01 -5.403984729748e-02 9.999738645903e-01 4.859485810390e-04 -7.206933692422e-03 -2.921968648686e-01
"""  # noqa: E501


@pytest.mark.parametrize(
    ("folder", "line", "edit", "message"),
    [
        (
            "image_0",
            1,
            lambda p: p.replace(" 0.000000000000e+00 6.07", " 1.500000000000e+00 6.07", 1),
            "skew 1.5",
        ),
        (
            "image_2",
            3,
            lambda p: p.replace("1.000000000000e+00 3.77", "2.000000000000e+00 3.77"),
            "0 0 2, not",
        ),
        (
            "image_2",
            3,
            lambda p: p.replace("0.000000000000e+00 1.000000000000e+00 3.7", "0.1 1.0 3.7"),
            "0.1 1",
        ),
        (
            "image_0",
            1,
            lambda p: p.replace("0.000000000000e+00 7.18", "-2.5 7.18", 1),
            "-2.5 below the diagonal",
        ),
    ],
    ids=["p0-skew", "p2-third-row-scaled", "p2-third-row-tilted", "p0-lower-triangle"],
)
def test_kitti_projection_must_be_a_rectified_pinhole(
    tmp_path: Path, folder: str, line: int, edit: Callable[[str], str], message: str
) -> None:
    root = tmp_path / "sequences" / "00"
    for k in range(2):
        write_png(root / folder / f"{k:06d}.png", k)
    (root / "calib.txt").write_text(KITTI_CALIB)
    camera = open_dataset(root).camera  # the published file: baselines and Tr are fine
    assert (camera.fx, camera.cx, camera.cy) == (718.856, 607.1928, 185.2157)
    lines = KITTI_CALIB.splitlines()
    lines[line - 1] = edit(lines[line - 1])
    (root / "calib.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(
        CalibrationError, match=rf"calib\.txt:{line}: P{line - 1} is not a rectified pinhole"
    ) as error:
        open_dataset(root)
    assert message in str(error.value)


#: cam0's T_BS of EuRoC MH_01_easy as published (Kalibr, about 10 significant digits).
EUROC_T_BS = [
    [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
    [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
    [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
    [0.0, 0.0, 0.0, 1.0],
]


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda m: m @ np.diag([1.1, 1.1, 1.1, 1.0]), r"max \|R Rᵀ - I\| = 0\.21"),
        (lambda m: m @ np.diag([1.0, 1.0, -1.0, 1.0]), r"det R = -1"),
        (lambda m: m + np.diag([0.0, 0.05, 0.0, 0.0]), r"max \|R Rᵀ - I\|"),
    ],
    ids=["scaled", "reflection", "sheared"],
)
def test_euroc_t_bs_rotation_must_be_orthonormal(
    tmp_path: Path, change: Callable[[np.ndarray], np.ndarray], message: str
) -> None:
    make_euroc(tmp_path)
    gt = tmp_path / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    gt.parent.mkdir(parents=True)
    gt.write_text("".join(f"{1403636579763555584 + 5_000_000 * j},1,2,3,1,0,0,0\n" for j in range(40)))
    sensor = tmp_path / "mav0" / "cam0" / "sensor.yaml"
    head = sensor.read_text()

    def write(matrix: np.ndarray) -> None:
        data = ", ".join(repr(float(v)) for v in matrix.ravel())
        sensor.write_text(f"# cam0\n{head}T_BS:\n  cols: 4\n  rows: 4\n  data: [{data}]\n")

    write(np.array(EUROC_T_BS))
    assert open_dataset(tmp_path).has_groundtruth  # the published matrix, orthonormal to ~1e-9
    write(change(np.array(EUROC_T_BS)))
    with pytest.raises(CalibrationError, match=rf"sensor\.yaml:4: T_BS is not a rigid transform.*{message}"):
        open_dataset(tmp_path)


# --- error messages stay short -------------------------------------------------------------------------

HUGE = "9" * 1_000_000 + "x"


@pytest.mark.parametrize(
    ("index", "line", "open_it"),
    [
        ("rgb.txt", f"{HUGE} rgb/a.png", lambda root: open_dataset(root, "tum")),
        ("mav0/cam0/data.csv", HUGE, lambda root: open_dataset(root, "euroc")),
        ("times.txt", HUGE, lambda root: read_times(root / "times.txt")),
    ],
    ids=["tum-rgb-txt", "euroc-data-csv", "times-txt"],
)
def test_a_huge_field_is_not_rendered_in_the_error(
    tmp_path: Path, index: str, line: str, open_it: Callable[[Path], Any]
) -> None:
    (tmp_path / "rgb").mkdir()
    (tmp_path / index).parent.mkdir(parents=True, exist_ok=True)
    (tmp_path / index).write_text(f"{line}\n")
    with pytest.raises(SymbioError) as error:
        open_it(tmp_path)
    assert index in str(error.value) and len(str(error.value)) < 300 + len(str(tmp_path))


# --- random bytes as image files -----------------------------------------------------------------------

_SAMPLE = noise(7)
VALID_ENCODINGS = {
    ext: cv2.imencode(ext, _SAMPLE)[1].tobytes() for ext in (".png", ".jpg", ".bmp", ".tiff", ".webp", ".ppm")
}


def _mutate(ext: str, edits: list[tuple[int, int]], cut: int | None) -> bytes:
    data = bytearray(VALID_ENCODINGS[ext])
    for position, value in edits:
        data[position % len(data)] = value
    return bytes(data if cut is None else data[: cut % (len(data) + 1)])


#: Garbage, valid files with bytes overwritten or cut short, and PNGs whose header declares any size.
IMAGE_BYTES = st.one_of(
    st.binary(max_size=2048),
    st.builds(
        _mutate,
        st.sampled_from(sorted(VALID_ENCODINGS)),
        st.lists(st.tuples(st.integers(0, 1 << 20), st.integers(0, 255)), max_size=8),
        st.none() | st.integers(0, 1 << 20),
    ),
    st.tuples(st.integers(1, (1 << 31) - 1), st.integers(1, (1 << 31) - 1)),
)


@pytest.fixture(scope="module")
def fuzzed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Dataset, Path]:
    root = tmp_path_factory.mktemp("fuzz") / CAFE
    make_folder(root)
    return open_dataset(root), root / f"{BAD_NAME}1.png"


@settings(max_examples=FUZZ_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(IMAGE_BYTES)
def test_random_bytes_as_an_image_are_decoded_or_skipped(
    fuzzed: tuple[Dataset, Path], data: bytes | tuple[int, int]
) -> None:
    dataset, path = fuzzed
    declared = data if isinstance(data, tuple) else None
    path.write_bytes(png_with_header_size(*declared) if declared else data)  # type: ignore[arg-type]
    dataset.skipped.clear()
    image = dataset.read_image(1)
    if image is None:
        [skipped] = dataset.skipped
        assert skipped.cause in SKIP_CAUSES and "im\\xff1.png" in skipped.reason
        if declared is not None and declared != (W, H):  # refused by its header, never decoded
            assert skipped.cause == "wrong image size"
    else:
        assert image.dtype == np.uint8 and image.shape[:2] == (H, W) and not dataset.skipped
    decoded = decode_image(path)
    assert decoded is None or (decoded.dtype == np.uint8 and decoded.size <= 3 * 100_000_000)


def test_a_whole_run_on_a_dataset_and_out_folder_with_non_utf8_names(
    small_loop_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Reading is not enough: the run's messages, metrics, plots and report name the folders too."""
    scene = Path(os.fsdecode(bytes(tmp_path) + b"/sc\xe9ne"))
    scene.symlink_to(small_loop_scene)
    out = Path(os.fsdecode(bytes(tmp_path) + b"/r\xfcn"))
    argv = ["run", str(scene), "--frontend", "replay", "--set", f"trajectory={scene / 'groundtruth.txt'}"]
    assert symbio_main([*argv, "--no-loops", "--no-progress", "--max-frames", "30", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "sc\\xe9ne" in printed and "r\\xfcn" in printed
    import json

    metrics = json.loads((out / "metrics.json").read_text(encoding="utf-8"))
    assert metrics["complete"] is True and metrics["dataset"].endswith("sc\\xe9ne")
    assert "sc\\xe9ne" in (out / "report.html").read_text(encoding="utf-8")
