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
import re
import shutil
import subprocess
import sys
import tracemalloc
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from eval import checkpoint
from eval.cli import main as symbio_main
from eval.components import load_components
from eval.inject import KINDS, InjectionSpec
from eval.paper.table import TableConfig, load_experiment_config
from frontends import safe_yaml
from frontends.config import load_config
from frontends.datasets import open_dataset
from frontends.datasets.calib import read_intrinsics
from frontends.datasets.euroc import read_groundtruth, read_image_list
from frontends.datasets.kitti import read_projection_matrices
from frontends.errors import CalibrationError, ConfigError, SymbioError
from frontends.gt_loops import LoopLabelConfig, read_loop_pairs
from frontends.trajectory_io import read_kitti_poses, read_times, read_tum
from lcd.symbiolcd import load_table
from lcd.vocabulary import Vocabulary
from slam_backend.pipeline import LoopClosingConfig
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
        "mac",
    ]
)
RUN_HEADER_VALUES = st.recursive(
    st.one_of(
        st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=8),
        st.sampled_from(
            [checkpoint.FORMAT, checkpoint.VERSION, "checkpoint-000050.pkl", "../graph.json", "0" * 64]
        ),
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


# --- bounded YAML: alias bombs and deep nesting at every entry point (issue 41) ---------------------

#: Nine lists of nine aliases to the list before: 9**9 "lol"s once expanded (billion laughs).
BOMB_LINES = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]'] + [
    f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, 9)
]
#: The same as one flow value, for ``--set key=VALUE``.
BOMB_VALUE = "[" + ", ".join(line.split(": ", 1)[1] for line in BOMB_LINES) + "]"
DEEP_VALUE = "[" * 50_000 + "]" * 50_000
MEMORY_LIMIT = 200 * 2**20


def refused_within_memory(call: Callable[[], object], error: type[Exception], match: str) -> str:
    """The message of the ``error`` that ``call`` raises, allocating under MEMORY_LIMIT on the way.
    (The bombs fail in milliseconds; their speed is left to benchmarks, their memory is not.)"""
    tracemalloc.start()
    try:
        with pytest.raises(error, match=match) as info:
            call()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < MEMORY_LIMIT, f"peak {peak / 2**20:.0f} MiB"
    message = str(info.value)
    assert len(message) < 400, f"error message of {len(message)} characters"
    return message


def names_an_alias_line(message: str, path: Path) -> None:
    """The message names ``path`` and a line that holds an alias."""
    found = re.search(rf"{re.escape(str(path))}:(\d+): ", message)
    assert found, message
    assert "*a" in path.read_text().splitlines()[int(found.group(1)) - 1], message


@dataclass(frozen=True)
class _Knobs:
    ratio: float = 0.5
    sizes: tuple[int, ...] = ()


def _calib(path: Path) -> object:
    return read_intrinsics(path)


def _run_config(path: Path) -> object:
    return load_components(path, [], {})


def _table_config(path: Path) -> object:
    return load_experiment_config(TableConfig, path)


def _config(path: Path) -> object:
    return load_config(_Knobs, path)


FILE_READERS = [
    ("intrinsics.yaml", _calib, CalibrationError, "fx: 500\nfy: 500\ncx: 320\ncy: 240\n"),
    ("run.yaml", _run_config, ConfigError, "detector:\n  name: vbow\n"),
    ("table.yaml", _table_config, ConfigError, "datasets: [{name: a, synthetic: loop}]\n"),
    ("config.yaml", _config, ConfigError, "ratio: 0.5\n"),
]


@pytest.mark.parametrize(("name", "read", "error", "valid"), FILE_READERS)
def test_an_alias_bomb_is_refused_at_its_alias(
    tmp_path: Path, name: str, read: Callable[[Path], object], error: type[Exception], valid: str
) -> None:
    """``--calib``, ``symbio run --config``, ``eval table --config``, ``load_config``: one bounded loader."""
    path = tmp_path / name
    path.write_text(valid + "\n".join(BOMB_LINES) + "\n")
    names_an_alias_line(refused_within_memory(lambda: read(path), error, "alias"), path)


@pytest.mark.parametrize(("name", "read", "error", "valid"), FILE_READERS)
def test_deep_nesting_is_refused(
    tmp_path: Path, name: str, read: Callable[[Path], object], error: type[Exception], valid: str
) -> None:
    path = tmp_path / name
    path.write_text(f"{valid}deep: {DEEP_VALUE}\n")
    line = valid.count("\n") + 1
    refused_within_memory(lambda: read(path), error, rf"{re.escape(str(path))}:{line}: nested deeper than")


def test_symbio_run_refuses_an_alias_bomb(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Through the CLI: exit status 2 and one line naming the file and the alias's line."""
    path = tmp_path / "run.yaml"
    path.write_text("detector:\n  name: vbow\n" + "\n".join(BOMB_LINES) + "\n")
    argv = ["run", str(tmp_path / "scene"), "--config", str(path), "--out", str(tmp_path / "out")]
    assert symbio_main(argv) == 2
    error = capsys.readouterr().err
    assert error.startswith("symbio: error: ") and len(error) < 400, error
    names_an_alias_line(error, path)


def _run_set(item: str) -> object:
    """``symbio run --set loop_closing.KEY=VALUE`` as ``eval.run.build_slam`` applies it."""
    return load_config(LoopClosingConfig, None, load_components(None, [item], {}).of("loop_closing"))


SET_READERS = [
    ("load_config --set", lambda item: load_config(_Knobs, None, [item])),
    ("eval table --set", lambda item: load_experiment_config(TableConfig, TABLE_YAML, [item])),
    ("symbio run --set", _run_set),
]
TABLE_YAML = Path(__file__).resolve().parent.parent / "eval" / "configs" / "smoke.yaml"


@pytest.mark.parametrize("value", [BOMB_VALUE, DEEP_VALUE], ids=["alias-bomb", "deep"])
@pytest.mark.parametrize(("what", "apply"), SET_READERS, ids=[r[0] for r in SET_READERS])
def test_a_set_value_goes_through_the_same_loader(
    what: str, apply: Callable[[str], object], value: str
) -> None:
    key = "loop_closing.proposal_ratio" if "run" in what else "repeats" if "table" in what else "ratio"
    message = refused_within_memory(
        lambda: apply(f"{key}={value}"), ConfigError, "values once aliases are expanded|nested deeper than"
    )
    assert "override" in message or "--set" in message, message


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("a: &a x\nb: [" + ", ".join(["*a"] * 101) + "]\n", r":2: more than 100 aliases"),
        ("a: &a [1, *a]\n", r":1: alias \*a refers to itself"),
        ("a: &a " + "[" * 60 + "]" * 60 + "\nb: " + "[" * 50 + "*a" + "]" * 50 + "\n", r":2: nested deeper"),
        ("a: 1" + "0" * 5000 + "\n", r":1: invalid value \(Exceeds the limit"),
    ],
    ids=["alias-count", "self-reference", "depth-through-alias", "huge-integer"],
)
def test_the_loader_limits(tmp_path: Path, text: str, reason: str) -> None:
    path = tmp_path / "config.yaml"
    path.write_text(text)
    refused_within_memory(lambda: load_config(_Knobs, path), ConfigError, rf"config\.yaml{reason}")


ANCHORED = st.lists(
    st.one_of(
        st.tuples(st.sampled_from(["a", "b", "c", "d"]), TOKENS).map(lambda kv: f"{kv[0]}: {kv[1]}"),
        st.sampled_from(["e: &x [1, 2]", "f: *x", "g: {<<: {h: 1}, h: 2}", "i: &y {j: *x}", "k: [*y, *y]"]),
        st.text(max_size=20),
    ),
    max_size=8,
).map("\n".join)


@given(st.one_of(yaml_text(), ANCHORED))
def test_the_bounded_loader_agrees_with_pyyaml(text: str) -> None:
    """Whatever ``frontends.safe_yaml`` accepts, it reads as ``yaml.safe_load`` does; what it refuses
    is a ``YamlInputError`` (never a traceback from inside PyYAML)."""
    try:
        data, _ = safe_yaml.load(text)
    except safe_yaml.YamlInputError:
        return
    assert repr(data) == repr(yaml.safe_load(text))


REPO = Path(__file__).resolve().parent.parent
BOMB_COMMANDS = {
    "run --config": ["run", "{images}", "--calib", "{calib}", "--config", "{bomb}", "--out", "{out}"],
    "run --calib": ["run", "{images}", "--calib", "{bomb}", "--out", "{out}"],
    "run --set": [
        "run",
        "{images}",
        "--calib",
        "{calib}",
        "--set",
        "detector.threshold={value}",
        "--out",
        "{out}",
    ],
    "datasets info --calib": ["datasets", "info", "{images}", "--calib", "{bomb}"],
    "eval lcd --calib": ["eval", "lcd", "{images}", "--calib", "{bomb}"],
    "eval table --config": ["eval", "table", "--config", "{bomb}", "--out", "{out}"],
    "eval table --set": [
        "eval",
        "table",
        "--config",
        "{table}",
        "--set",
        "repeats={value}",
        "--out",
        "{out}",
    ],
    "demo --set": ["demo", "--set", "seed={value}", "--out", "{out}"],
}


@pytest.mark.parametrize("command", list(BOMB_COMMANDS))
def test_every_command_refuses_an_alias_bomb_in_a_small_process(command: str, tmp_path: Path) -> None:
    """The whole ``symbio`` process, not only the parser, stays small: a command checks its options
    and files before it loads the pipeline's libraries (gtsam, pycolmap, scikit-learn)."""
    images = tmp_path / "images"
    images.mkdir()
    for k in range(3):
        assert cv2.imwrite(str(images / f"{k:06d}.png"), np.zeros((48, 64), np.uint8))
    calib = tmp_path / "calib.yaml"
    calib.write_text("fx: 50\nfy: 50\ncx: 32\ncy: 24\nwidth: 64\nheight: 48\n")
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text("\n".join(BOMB_LINES) + "\n")
    table = REPO / "eval" / "configs" / "smoke.yaml"
    fields = {"images": images, "calib": calib, "bomb": bomb, "out": tmp_path / "out", "table": table}
    argv = [part.format(value=BOMB_VALUE, **fields) for part in BOMB_COMMANDS[command]]
    # VmHWM, not ru_maxrss: the latter keeps the forking pytest process's peak across exec. Less the
    # file-backed pages still mapped (the libraries' code): how many of those are resident depends on
    # the page cache (a freshly installed venv: +50 MB), the process's own memory does not.
    probe = (
        "import json, re, sys\nfrom eval.cli import main\nrc = main(json.loads(sys.argv[1]))\n"
        "status = open('/proc/self/status').read()\n"
        "kb = {k: int(re.search(k + r':\\s*(\\d+)', status).group(1)) for k in ('VmHWM', 'RssFile')}\n"
        "print(json.dumps([rc, kb['VmHWM'] - kb['RssFile']]))"
    )
    child = subprocess.run(
        [sys.executable, "-c", probe, json.dumps(argv)], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    rc, max_rss_kb = json.loads(child.stdout.strip().splitlines()[-1])
    assert rc == 2 and child.stderr.startswith("symbio: error: ") and "Traceback" not in child.stderr
    assert len(child.stderr) < 400
    # The pipeline's libraries alone take ~165 MB of it (gtsam, pycolmap, scikit-learn), the parsers ~70.
    assert max_rss_kb < 120 * 1024, f"{command}: {max_rss_kb / 1024:.0f} MB"
    assert not (tmp_path / "out").exists()  # refused before anything was written
