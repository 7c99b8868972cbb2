"""Camera intrinsics from YAML files.

Accepted layouts (detected from the keys):
- ours: ``fx fy cx cy width height distortion`` (distortion = OpenCV order k1 k2 p1 p2 [k3]);
- ORB-SLAM settings (``Camera.fx`` ... ``Camera.k1`` ...; the ``%YAML:1.0`` header is allowed);
- EuRoC / Kalibr ``sensor.yaml`` (``intrinsics: [fu, fv, cu, cv]``, ``distortion_coefficients``,
  ``resolution: [w, h]``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import yaml

from frontends import safe_yaml
from frontends.errors import CalibrationError
from frontends.safe_yaml import short_repr
from frontends.types import CameraIntrinsics

#: File names a dataset folder may hold its intrinsics in, checked in this order.
INTRINSICS_FILE_NAMES = ("intrinsics.yaml", "intrinsics.yml", "camera.yaml", "calib.yaml")


class YamlMapping(dict[str, Any]):
    """A YAML file's top-level mapping and the 1-based line of each (dotted) key, for errors."""

    def __init__(self, data: dict[str, Any], lines: dict[str, int]) -> None:
        super().__init__(data)
        self.lines = lines


def read_yaml_file(path: Path, error: type[CalibrationError] = CalibrationError) -> YamlMapping:
    """A calibration YAML's mapping, read with the bounded loader (``frontends.safe_yaml``)."""
    try:
        text = safe_yaml.read_text(path)
        # OpenCV FileStorage headers ("%YAML:1.0") and "!!opencv-matrix" tags are not plain YAML;
        # the header becomes a blank line so that errors keep the file's line numbers.
        lines = ("" if line.startswith("%YAML") else line for line in text.split("\n"))
        data, key_lines = safe_yaml.load("\n".join(lines).replace("!!opencv-matrix", ""))
    except safe_yaml.YamlInputError as exc:
        raise error(path, exc.reason, exc.line) from None
    if not isinstance(data, dict):
        raise error(path, "expected a mapping of calibration keys")
    return YamlMapping(data, key_lines)


def _line(data: dict[str, Any], key: str) -> int | None:
    return data.lines.get(key) if isinstance(data, YamlMapping) else None


def _number(data: dict[str, Any], key: str, path: Path, default: float | None = None) -> float:
    if key not in data:
        if default is not None:
            return default
        raise CalibrationError(path, f"missing key {key!r}")
    number = safe_yaml.number(data[key])
    if number is None or not math.isfinite(number):
        raise CalibrationError(
            path, f"{key!r} must be a finite number, got {short_repr(data[key])}", _line(data, key)
        )
    return number


def _numbers(data: dict[str, Any], key: str, path: Path) -> list[float]:
    """The list of numbers at ``key`` (a plain list or an OpenCV matrix); empty if missing or null."""
    value = data.get(key) or []
    if isinstance(value, dict) and "data" in value:  # OpenCV matrix
        value = value["data"]
    numbers = [safe_yaml.number(v) for v in value] if isinstance(value, (list, tuple)) else [None]
    if any(n is None or not math.isfinite(n) for n in numbers):
        raise CalibrationError(
            path, f"{key!r} must be a list of finite numbers, got {short_repr(value)}", _line(data, key)
        )
    return [n for n in numbers if n is not None]


def _size(data: dict[str, Any], key: str, path: Path) -> int:
    """An image dimension; 0 when missing (the caller may fill it in)."""
    value = data.get(key)
    if value is None:
        return 0
    if isinstance(value, str) and value.isascii() and value.strip().isdigit():
        value = int(value)  # a quoted integer ("640"), accepted as it always was
    number = safe_yaml.number(value)
    if number is None or not number.is_integer():
        raise CalibrationError(path, f"{key!r} must be an integer, got {short_repr(value)}", _line(data, key))
    return int(number)


def intrinsics_from_mapping(
    data: dict[str, Any], path: Path, image_size: tuple[int, int] | None = None
) -> CameraIntrinsics:
    """Intrinsics from an already-parsed YAML mapping; ``image_size`` fills a missing resolution.

    Errors name the key's line when ``data`` comes from ``read_yaml_file``.
    """
    source = str(path)
    if "intrinsics" in data:  # EuRoC / Kalibr
        fx, fy, cx, cy = _exactly(
            _numbers(data, "intrinsics", path), 4, "intrinsics", path, _line(data, "intrinsics")
        )
        distortion = _numbers(data, "distortion_coefficients", path)
        size = _numbers(data, "resolution", path)
        if size and (len(size) != 2 or not all(v.is_integer() for v in size)):
            raise CalibrationError(
                path, f"'resolution' must be [width, height] in pixels, got {size}", _line(data, "resolution")
            )
        width, height = (int(size[0]), int(size[1])) if size else (0, 0)
    elif "Camera.fx" in data or "Camera1.fx" in data:  # ORB-SLAM2/3 settings
        prefix = "Camera." if "Camera.fx" in data else "Camera1."
        fx, fy, cx, cy = (_number(data, prefix + k, path) for k in ("fx", "fy", "cx", "cy"))
        distortion = [_number(data, prefix + k, path, 0.0) for k in ("k1", "k2", "p1", "p2")]
        if prefix + "k3" in data:
            distortion.append(_number(data, prefix + "k3", path))
        width = _size(data, "Camera.width" if "Camera.width" in data else "Camera1.width", path)
        height = _size(data, "Camera.height" if "Camera.height" in data else "Camera1.height", path)
    else:
        fx, fy, cx, cy = (_number(data, k, path) for k in ("fx", "fy", "cx", "cy"))
        distortion = _numbers(data, "distortion", path)
        width, height = _size(data, "width", path), _size(data, "height", path)
    if not width or not height:
        if image_size is None:
            raise CalibrationError(path, "image size missing: add width and height")
        width, height = image_size
    if all(d == 0 for d in distortion):
        distortion = []
    return CameraIntrinsics(fx, fy, cx, cy, width, height, tuple(distortion), source=source)


def _exactly(values: list[float], n: int, key: str, path: Path, line: int | None) -> list[float]:
    if len(values) != n:
        raise CalibrationError(path, f"{key!r} must have {n} values, got {len(values)}", line)
    return values


def read_intrinsics(path: str | Path, image_size: tuple[int, int] | None = None) -> CameraIntrinsics:
    path = Path(path)
    return intrinsics_from_mapping(read_yaml_file(path), path, image_size)


def find_intrinsics_file(folder: Path) -> Path | None:
    for name in INTRINSICS_FILE_NAMES:
        if (folder / name).is_file():
            return folder / name
    return None


def write_intrinsics(path: str | Path, camera: CameraIntrinsics) -> None:
    Path(path).write_text(yaml.safe_dump(camera.as_dict(), sort_keys=False), encoding="utf-8")
