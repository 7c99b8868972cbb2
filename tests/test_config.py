from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pytest

from frontends.config import config_to_dict, load_config
from frontends.errors import CalibrationError, ConfigError
from frontends.registry import Registry
from frontends.types import CameraIntrinsics


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
