"""Fuzzing every file parser: only the project's documented errors escape, and they name the file.

Inputs are line-structured texts built from valid rows, mutated rows (missing / extra columns, NaN,
inf, huge numbers, words, empty fields), comments, blank lines and raw garbage, plus raw bytes for
the binary formats. A parser may accept an input (then its output must be finite and well shaped)
or raise a ``frontends.errors.SymbioError`` whose message names the file; anything else fails.

Budget: ``HYPOTHESIS_PROFILE=fuzz`` runs 10 000 inputs per parser (minutes); the default ``ci``
profile runs 150 so ``make test`` stays fast.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from eval import checkpoint
from eval.inject import KINDS, InjectionSpec
from frontends.config import load_config
from frontends.datasets import open_dataset
from frontends.datasets.calib import read_intrinsics
from frontends.datasets.euroc import read_groundtruth, read_image_list
from frontends.datasets.kitti import read_projection_matrices
from frontends.errors import ConfigError, SymbioError
from frontends.gt_loops import LoopLabelConfig, read_loop_pairs
from frontends.trajectory_io import read_kitti_poses, read_times, read_tum
from lcd.symbiolcd import load_table
from lcd.vocabulary import Vocabulary
from slam_backend.posegraph import GtsamPoseGraph

settings.register_profile("ci", max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.register_profile(
    "fuzz", max_examples=10_000, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

TOKENS = st.sampled_from(
    ["0", "1", "-1", "0.5", "1e3", "1e999", "-1e999", "nan", "NaN", "inf", "-inf", "abc", "", "1,2", "0x10",
     "3.", ".5", "1e", "--1", "\t", "é", "1_000"]
)  # fmt: skip


def _row(columns: int) -> st.SearchStrategy[str]:
    valid = st.lists(
        st.floats(-1e6, 1e6, allow_nan=False).map(lambda v: f"{v:.6g}"), min_size=columns, max_size=columns
    )
    mutated = st.lists(TOKENS, min_size=0, max_size=columns + 3)
    return st.one_of(valid, valid, mutated).map(" ".join)


def table_text(columns: int) -> st.SearchStrategy[str]:
    line = st.one_of(_row(columns), _row(columns), st.just(""), st.just("# comment"), st.text(max_size=40))
    clean = st.lists(_row(columns).filter(lambda r: "nan" not in r.lower()), max_size=25)
    # Mostly-valid files too, so the accepting path (and its output checks) runs as well.
    return st.one_of(st.lists(line, max_size=25), clean).map("\n".join)


@pytest.fixture(scope="module")
def scratch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One folder per module, emptied for every input (a folder per input left ~190 000 behind)."""
    return tmp_path_factory.mktemp("fuzz")


def _write(scratch: Path, text: str | bytes, name: str) -> Path:
    folder = scratch / "input"
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir()
    path = folder / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8", errors="surrogatepass")
    return path


def accepts_or_names_the_file(parse: Callable[[Path], Any], path: Path) -> Any:
    try:
        return parse(path)
    except SymbioError as exc:
        assert path.name in str(exc), f"error does not name the file: {exc}"
        return None


def _finite_positions(trajectory: Any) -> None:
    assert (
        np.isfinite(trajectory.positions_xyz).all() and np.isfinite(trajectory.orientations_quat_wxyz).all()
    )


@given(table_text(8))
def test_tum_trajectory(scratch: Path, text: str) -> None:
    trajectory = accepts_or_names_the_file(read_tum, _write(scratch, text, "groundtruth.txt"))
    if trajectory is not None:
        _finite_positions(trajectory)
        assert np.all(np.diff(trajectory.timestamps) > 0)


@given(table_text(12))
def test_kitti_poses(scratch: Path, text: str) -> None:
    trajectory = accepts_or_names_the_file(read_kitti_poses, _write(scratch, text, "00.txt"))
    if trajectory is not None:
        _finite_positions(trajectory)


@given(table_text(1))
def test_times(scratch: Path, text: str) -> None:
    times = accepts_or_names_the_file(read_times, _write(scratch, text, "times.txt"))
    if times is not None:
        assert np.isfinite(times).all()


@given(table_text(2))
def test_loop_pairs(scratch: Path, text: str) -> None:
    pairs = accepts_or_names_the_file(
        lambda p: read_loop_pairs(p, num_frames=50), _write(scratch, text, "pairs.txt")
    )
    if pairs is not None:
        assert pairs.ndim == 2 and pairs.shape[1] == 2 and np.all((pairs >= 0) & (pairs < 50))


@given(st.lists(st.one_of(_row(12).map(lambda r: "P0: " + r), _row(12), st.text(max_size=30)), max_size=5))
def test_kitti_calib(scratch: Path, lines: list[str]) -> None:
    matrices = accepts_or_names_the_file(
        read_projection_matrices, _write(scratch, "\n".join(lines), "calib.txt")
    )
    if matrices:
        assert all(m.shape == (3, 4) and np.isfinite(m).all() for m in matrices.values())


def yaml_text() -> st.SearchStrategy[str]:
    key = st.sampled_from(
        ["fx", "fy", "cx", "cy", "width", "height", "distortion", "Camera.fx", "camera", "x"]
    )
    value = st.one_of(TOKENS, st.lists(TOKENS, max_size=6).map(lambda v: "[" + ", ".join(v) + "]"))
    line = st.one_of(st.tuples(key, value).map(lambda kv: f"{kv[0]}: {kv[1]}"), st.text(max_size=30))
    return st.lists(line, max_size=10).map("\n".join)


@given(yaml_text())
def test_intrinsics_yaml(scratch: Path, text: str) -> None:
    camera = accepts_or_names_the_file(read_intrinsics, _write(scratch, text, "intrinsics.yaml"))
    if camera is not None:
        assert camera.fx > 0 and camera.fy > 0 and camera.width > 0 and camera.height > 0


@given(yaml_text().map(lambda t: t.replace("fx", "max_distance").replace("fy", "min_time_gap")))
def test_config_yaml(scratch: Path, text: str) -> None:
    accepts_or_names_the_file(
        lambda p: load_config(LoopLabelConfig, p, []), _write(scratch, text, "config.yaml")
    )


@given(st.lists(st.one_of(_row(2).map(lambda r: r.replace(" ", ",")), st.text(max_size=30)), max_size=12))
def test_euroc_csv(scratch: Path, lines: list[str]) -> None:
    folder = _write(scratch, "#timestamp [ns],filename\n" + "\n".join(lines), "data.csv").parent
    accepts_or_names_the_file(read_image_list, folder / "data.csv")


@given(st.lists(st.one_of(_row(17).map(lambda r: r.replace(" ", ",")), st.text(max_size=30)), max_size=12))
def test_euroc_groundtruth(scratch: Path, lines: list[str]) -> None:
    result = accepts_or_names_the_file(
        read_groundtruth, _write(scratch, "#header\n" + "\n".join(lines), "data.csv")
    )
    if result is not None:
        stamps, poses = result
        assert len(stamps) == len(poses)


@given(table_text(3))
def test_tum_rgb_list(scratch: Path, text: str) -> None:
    """A TUM folder whose rgb.txt is garbage: opening it fails cleanly or lists what it can."""
    root = _write(scratch, "# rgb\n" + text, "rgb.txt").parent
    (root / "rgb").mkdir()
    accepts_or_names_the_file(lambda p: open_dataset(p.parent, "tum"), root / "rgb.txt")


def _npz(arrays: dict[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)  # type: ignore[arg-type]  # numpy stub types allow_pickle only
    return buffer.getvalue()


ARRAYS = st.dictionaries(
    st.sampled_from(["k", "levels", "centres", "parents", "weights", "features", "labels", "names", "x"]),
    st.one_of(
        st.integers(-3, 5).map(lambda v: np.array(v)),
        st.lists(st.integers(0, 255), max_size=40).map(lambda v: np.array(v, dtype=np.uint8)),
        st.lists(st.floats(allow_nan=True), max_size=12).map(np.array),
    ),
    max_size=6,
)


@given(st.one_of(st.binary(max_size=200), ARRAYS.map(_npz)))
def test_vocabulary_file(scratch: Path, data: bytes) -> None:
    accepts_or_names_the_file(Vocabulary.load, _write(scratch, data, "vocab.npz"))


@given(st.one_of(st.binary(max_size=200), ARRAYS.map(_npz)))
def test_symbiolcd_table(scratch: Path, data: bytes) -> None:
    accepts_or_names_the_file(load_table, _write(scratch, data, "table.npz"))


CHECKPOINT_KEYS = st.sampled_from(
    ["format", "version", "config", "keyframes", "loops", "mode", "id", "odometry", "covariance"]
)
JSON_VALUES = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=8)),
    lambda children: st.one_of(
        st.lists(children, max_size=4), st.dictionaries(CHECKPOINT_KEYS, children, max_size=5)
    ),
    max_leaves=20,
)


@given(st.one_of(st.text(max_size=200), JSON_VALUES.map(json.dumps)))
def test_pose_graph_checkpoint(scratch: Path, text: str) -> None:
    accepts_or_names_the_file(GtsamPoseGraph.load, _write(scratch, text, "graph.json"))


def test_truncated_npz_names_the_file(tmp_path: Path) -> None:
    """A vocabulary cut short mid-file (an interrupted download)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("k.npy", b"\x93NUMPY" + b"\x00" * 50)
    path = tmp_path / "cut.npz"
    path.write_bytes(buffer.getvalue()[:-10])
    with pytest.raises(SymbioError, match=r"cut\.npz"):
        Vocabulary.load(path)


RUN_HEADER_KEYS = st.sampled_from(
    [
        "format",
        "version",
        "frames",
        "next_index",
        "payload",
        "bytes",
        "sha256",
        "spec",
        "spec_hash",
        "dataset",
    ]
)
RUN_HEADER_VALUES = st.recursive(
    st.one_of(
        st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=8),
        st.sampled_from([checkpoint.FORMAT, checkpoint.VERSION, "checkpoint-000050.pkl", "../graph.json"]),
    ),
    lambda children: st.one_of(
        st.lists(children, max_size=4), st.dictionaries(RUN_HEADER_KEYS, children, max_size=10)
    ),
    max_leaves=25,
)  # fmt: skip


@given(st.one_of(st.text(max_size=200), RUN_HEADER_VALUES.map(json.dumps)))
def test_run_checkpoint_header(scratch: Path, text: str) -> None:
    """``symbio run --resume DIR``: the header, then the payload it names (size and hash first)."""
    path = _write(scratch, text, checkpoint.HEADER_FILE)
    try:
        header = checkpoint.read_header(path.parent)
        checkpoint.load_state(header, path.parent, None, None)  # type: ignore[arg-type]
    except SymbioError as exc:
        assert checkpoint.HEADER_FILE in str(exc) or str(path.parent) in str(exc), exc
    else:
        raise AssertionError("a fuzzed header loaded a state")


@given(st.lists(st.one_of(st.sampled_from(sorted(KINDS)), TOKENS, st.text(max_size=10)), max_size=5))
def test_inject_spec(parts: list[str]) -> None:
    """``--inject KIND[:RATE],...``: a spec or a ConfigError naming what is wrong."""
    text = ",".join(parts)
    try:
        spec = InjectionSpec.parse(text, 0)
    except ConfigError:
        return
    assert spec.faults and all(0.0 < fault.rate <= 1.0 and fault.kind in KINDS for fault in spec.faults)
