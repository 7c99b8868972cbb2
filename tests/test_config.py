from __future__ import annotations

import pickle
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from eval.components import load_components
from eval.paper.table import TableConfig, load_experiment_config
from frontends.config import Override, config_to_dict, load_config
from frontends.datasets.calib import read_intrinsics
from frontends.errors import CalibrationError, ConfigError
from frontends.registry import Registry
from frontends.types import CameraIntrinsics
from lcd.base import LOOP_DETECTORS
from slam_backend.pipeline import LoopClosingConfig

SMOKE_TABLE = Path(__file__).resolve().parent.parent / "eval" / "configs" / "smoke.yaml"


@dataclass(frozen=True)
class Inner:
    radius: float = 1.0
    name: str = "a"


@dataclass(frozen=True)
class Outer:
    count: int = 3
    ratio: float = 0.5
    flag: bool = False
    sizes: tuple[int, ...] = (1, 2)
    label: str | None = None
    inner: Inner = field(default_factory=Inner)


def test_defaults_yaml_then_overrides(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("count: 7\ninner:\n  radius: 2\nsizes: [4, 5, 6]\n")
    config = load_config(Outer, path, ["ratio=0.25", "inner.name=b", "label=x"])
    assert config == Outer(count=7, ratio=0.25, sizes=(4, 5, 6), label="x", inner=Inner(radius=2.0, name="b"))
    assert config_to_dict(config)["sizes"] == [4, 5, 6]


def test_exponents_without_a_dot_are_numbers(tmp_path: Path) -> None:
    # YAML 1.1 reads "1e-6" as a string; a float field takes it as the number it means.
    path = tmp_path / "c.yaml"
    path.write_text("ratio: 2E3\ninner:\n  radius: -1.5e-2\n")
    assert load_config(Outer, path, []) == Outer(ratio=2000.0, inner=Inner(radius=-0.015))
    assert load_config(Outer, None, ["ratio=1e-6"]).ratio == 1e-6
    assert load_config(Outer, None, ["inner.name=1e-6"]).inner.name == "1e-6"  # a string field keeps it
    with pytest.raises(ConfigError, match="expected an integer"):
        load_config(Outer, None, ["count=1e3"])


def test_unknown_key_names_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("count: 7\ninner:\n  radius: 2\n  colour: red\n")
    with pytest.raises(ConfigError, match=r"c\.yaml:4: unknown key 'inner\.colour'"):
        load_config(Outer, path)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("count=1.5", "expected an integer"),
        ("flag=maybe", "expected true or false"),
        ("ratio=abc", "expected a number"),
        ("count", "expected key=value"),
        ("sizes=3", "expected a list"),
    ],
)
def test_bad_override_values(override: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        load_config(Outer, None, [override])


def test_invalid_yaml_reports_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("count: 1\nratio: [1, 2\n")
    with pytest.raises(ConfigError, match=r"bad\.yaml:\d+: invalid YAML"):
        load_config(Outer, path)


def test_registry_lists_and_loads() -> None:
    registry: Registry[object] = Registry("thing", "symbio.test_things", {"path": "pathlib:Path"})
    assert registry.names() == ["path"]
    assert registry.load("path") is Path
    with pytest.raises(ConfigError, match="unknown thing 'nope'; installed: path"):
        registry.load("nope")


def test_registry_names_a_plugin_that_cannot_be_imported() -> None:
    registry: Registry[object] = Registry(
        "thing", "symbio.test_things", {"gone": "no_such_module:create", "typo": "pathlib:Pth"}
    )
    with pytest.raises(ConfigError, match=r"thing 'gone' \(no_such_module:create\) could not be loaded"):
        registry.load("gone")
    with pytest.raises(ConfigError, match="'typo'"):
        registry.load("typo")


@pytest.mark.parametrize(
    "kwargs",
    [
        {"fx": -1.0},
        {"fx": float("nan")},
        {"width": 0},
        {"distortion": (0.1, 0.2, 0.3)},
    ],
)
def test_camera_rejects_bad_values(kwargs: dict[str, object]) -> None:
    values: dict[str, object] = {
        "fx": 500.0,
        "fy": 500.0,
        "cx": 320.0,
        "cy": 240.0,
        "width": 640,
        "height": 480,
    }
    values.update(kwargs)
    with pytest.raises(CalibrationError):
        CameraIntrinsics(**values)  # type: ignore[arg-type]


def test_camera_resize_scales_intrinsics() -> None:
    camera = CameraIntrinsics(500.0, 510.0, 320.0, 240.0, 640, 480)
    half = camera.with_size(320, 240)
    assert (half.fx, half.fy, half.cx, half.cy) == (250.0, 255.0, 160.0, 120.0)


# --- bounded, strict YAML (issue 41): see also tests/test_fuzz_parsers.py for the alias bombs ------

CALIB_BASE = "cx: 320\ncy: 240\nwidth: 640\nheight: 480\n"


def test_duplicate_keys_name_both_lines(tmp_path: Path) -> None:
    config = tmp_path / "c.yaml"
    config.write_text("count: 1\ninner:\n  radius: 2\n  radius: 3\n")
    with pytest.raises(ConfigError, match=r"c\.yaml:4: duplicate key 'radius' \(lines 3 and 4\)"):
        load_config(Outer, config)
    calib = tmp_path / "cam.yaml"
    calib.write_text("fx: 500\nfy: 500\nfx: 510\n" + CALIB_BASE)
    with pytest.raises(CalibrationError, match=r"cam\.yaml:3: duplicate key 'fx' \(lines 1 and 3\)"):
        read_intrinsics(calib)
    with pytest.raises(ConfigError, match=r"override 'inner=\{radius: 1, radius: 2\}': duplicate key"):
        load_config(Outer, None, ["inner={radius: 1, radius: 2}"])
    # A merge ("<<") is not a duplicate: its keys are there to be overridden.
    config.write_text("inner: {<<: {radius: 2, name: b}, name: c}\n")
    assert load_config(Outer, config).inner == Inner(radius=2.0, name="c")


def test_orb_slam_calib_with_a_word_names_the_key_line(tmp_path: Path) -> None:
    path = tmp_path / "orb.yaml"
    path.write_text(
        "%YAML:1.0\n---\nCamera.fx: 500\nCamera.fy: 500\nCamera.cx: 320\nCamera.cy: 240\n"
        "Camera.k1: abc\nCamera.width: 640\nCamera.height: 480\n"
    )
    # Line 7 of the file: the "%YAML:1.0" header OpenCV writes is not dropped from the count.
    with pytest.raises(
        CalibrationError, match=r"orb\.yaml:7: 'Camera\.k1' must be a finite number, got 'abc'"
    ):
        read_intrinsics(path)
    path.write_text("fx: 500\nfy: 500\ndistortion: [0.1, .nan, 0, 0]\n" + CALIB_BASE)
    with pytest.raises(CalibrationError, match=r"orb\.yaml:3: 'distortion' must be a list of finite"):
        read_intrinsics(path)
    path.write_text("fx: 500\nfy: 500\n" + CALIB_BASE.replace("640", "640.5"))
    with pytest.raises(CalibrationError, match=r"orb\.yaml:5: 'width' must be an integer"):
        read_intrinsics(path)


def test_calib_reads_exponents_as_config_does(tmp_path: Path) -> None:
    """YAML 1.1 reads "5.25e2" as a string; ``--set fx=5.25e2`` took it, so does a calibration."""
    path = tmp_path / "cam.yaml"
    path.write_text("fx: 5.25e2\nfy: 5.3E2\ncx: 3.195e+2\ncy: 2.395e2\nwidth: 640\nheight: 480\n")
    camera = read_intrinsics(path)
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (525.0, 530.0, 319.5, 239.5)
    path.write_text("intrinsics: [5.25e2, 5.25e2, 320, 240]\nresolution: [640, 480]\n")
    assert read_intrinsics(path).fx == 525.0


def test_a_set_value_that_is_not_yaml_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match=r"override 'repeats=\[': invalid YAML"):
        load_experiment_config(TableConfig, SMOKE_TABLE, ["repeats=["])
    with pytest.raises(ConfigError, match=r"override 'sizes=\[1, 2': invalid YAML"):
        load_config(Outer, None, ["sizes=[1, 2"])


def test_run_config_errors_name_file_and_line(tmp_path: Path) -> None:
    """``symbio run --config``: the sections become overrides that remember their file and line."""
    path = tmp_path / "run.yaml"
    path.write_text("detector:\n  name: vbow\n  threshold: abc\nloop_closing:\n  proposal_ratio: [1, 2]\n")
    components = load_components(path, [], {})
    with pytest.raises(ConfigError, match=r"run\.yaml:3: 'threshold': expected a number, got 'abc'"):
        LOOP_DETECTORS.load(components.detector)(components.of("detector"))
    with pytest.raises(ConfigError, match=r"run\.yaml:5: 'proposal_ratio': expected a number"):
        load_config(LoopClosingConfig, None, components.of("loop_closing"))
    # Command-line overrides are named as typed, section included.
    components = load_components(None, ["detector.threshold=abc"], {})
    with pytest.raises(ConfigError, match=r"--set 'detector\.threshold=abc': 'threshold': expected a number"):
        LOOP_DETECTORS.load("vbow")(components.of("detector"))
    path.write_text("frontend:\n  name: mono-vo\ndetector:\n  name: vbwo\n")
    with pytest.raises(ConfigError, match=r"run\.yaml:4: unknown detector 'vbwo'; installed: .*vbow"):
        load_components(path, [], {})


def test_an_override_from_a_file_survives_pickling() -> None:
    """Overrides travel to worker processes: the file and line must come along."""
    item = Override("threshold=abc", "run.yaml:3")
    copy = pickle.loads(pickle.dumps(item))
    assert copy == "threshold=abc" and copy.where == "run.yaml:3"


def test_error_messages_do_not_render_huge_values(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text(f"count: '{'x' * 50_000}'\n")
    with pytest.raises(ConfigError, match=r"c\.yaml:1: 'count': expected an integer") as info:
        load_config(Outer, path)
    assert len(str(info.value)) < 200
    path.write_text(f"ratio: [{', '.join(['1'] * 20_000)}]\n")
    with pytest.raises(ConfigError, match=r"c\.yaml:1: 'ratio': expected a number") as info:
        load_config(Outer, path)
    assert len(str(info.value)) < 200
    path.write_text(f"fx: [{', '.join(['1'] * 20_000)}]\nfy: 500\n" + CALIB_BASE)
    with pytest.raises(CalibrationError, match=r"c\.yaml:1: 'fx' must be a finite number") as info:
        read_intrinsics(path)
    assert len(str(info.value)) < 200


def test_oversized_and_non_utf8_yaml_files(tmp_path: Path) -> None:
    big = tmp_path / "big.yaml"
    big.write_text("# padding\n" * 200_000)
    with pytest.raises(ConfigError, match=r"big\.yaml: larger than 1048576 bytes"):
        load_config(Outer, big)
    with pytest.raises(CalibrationError, match=r"big\.yaml: larger than 1048576 bytes"):
        read_intrinsics(big)
    latin = tmp_path / "latin.yaml"
    latin.write_bytes(b"count: 1\nlabel: caf\xe9\n")
    with pytest.raises(ConfigError, match=r"latin\.yaml:2: not UTF-8 text \(byte 0xe9\)"):
        load_config(Outer, latin)


def test_a_config_check_names_the_file_or_override(tmp_path: Path) -> None:
    """``__post_init__`` checks know no file; ``apply_mapping`` adds where the value came from."""
    path = tmp_path / "table.yaml"
    path.write_text("repeats: 0\ndatasets: [{name: a, synthetic: loop}]\n")
    with pytest.raises(ConfigError, match=r"table\.yaml: repeats must be >= 1"):
        load_experiment_config(TableConfig, path)
    with pytest.raises(ConfigError, match=r"override 'repeats=0': repeats must be >= 1"):
        load_experiment_config(TableConfig, SMOKE_TABLE, ["repeats=0"])
