"""Camera intrinsics from YAML files.

Accepted layouts (detected from the keys):
- ours: ``fx fy cx cy width height distortion`` (distortion = OpenCV order k1 k2 p1 p2 [k3]);
- ORB-SLAM settings (``Camera.fx`` ... ``Camera.k1`` ...; the ``%YAML:1.0`` header is allowed);
- EuRoC / Kalibr ``sensor.yaml`` (``intrinsics: [fu, fv, cu, cv]``, ``distortion_coefficients``,
  ``resolution: [w, h]``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from frontends.errors import CalibrationError
from frontends.types import CameraIntrinsics

#: File names a dataset folder may hold its intrinsics in, checked in this order.
INTRINSICS_FILE_NAMES = ("intrinsics.yaml", "intrinsics.yml", "camera.yaml", "calib.yaml")


def read_yaml_file(path: Path, error: type[CalibrationError] = CalibrationError) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(path, "file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise error(path, f"cannot read file ({exc})") from None
    # OpenCV FileStorage headers ("%YAML:1.0") and "!!opencv-matrix" tags are not plain YAML.
    lines = [line for line in text.splitlines() if not line.startswith("%YAML")]
    text = "\n".join(lines).replace("!!opencv-matrix", "")
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        raise error(
            path,
            f"invalid YAML ({getattr(exc, 'problem', exc)})",
            mark.line + 1 if mark is not None else None,
        ) from None
    if not isinstance(data, dict):
        raise error(path, "expected a mapping of calibration keys")
    return data


def _number(data: dict[str, Any], key: str, path: Path) -> float:
    if key not in data:
        raise CalibrationError(path, f"missing key {key!r}")
    value = data[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise CalibrationError(path, f"{key!r} must be a number, got {value!r}")
    return float(value)


def _numbers(value: Any, key: str, path: Path) -> list[float]:
    if isinstance(value, dict) and "data" in value:  # OpenCV matrix
        value = value["data"]
    if not isinstance(value, (list, tuple)) or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value
    ):
        raise CalibrationError(path, f"{key!r} must be a list of numbers, got {value!r}")
    return [float(v) for v in value]


def intrinsics_from_mapping(
    data: dict[str, Any], path: Path, image_size: tuple[int, int] | None = None
) -> CameraIntrinsics:
    """Intrinsics from an already-parsed YAML mapping; ``image_size`` fills a missing resolution."""
    source = str(path)
    if "intrinsics" in data:  # EuRoC / Kalibr
        fx, fy, cx, cy = _exactly(_numbers(data["intrinsics"], "intrinsics", path), 4, "intrinsics", path)
        distortion = _numbers(data.get("distortion_coefficients", []), "distortion_coefficients", path)
        size = data.get("resolution")
        width, height = (
            _exactly(_numbers(size, "resolution", path), 2, "resolution", path) if size else (0, 0)
        )
    elif "Camera.fx" in data or "Camera1.fx" in data:  # ORB-SLAM2/3 settings
        prefix = "Camera." if "Camera.fx" in data else "Camera1."
        fx, fy, cx, cy = (_number(data, prefix + k, path) for k in ("fx", "fy", "cx", "cy"))
        distortion = [float(data.get(prefix + k, 0.0)) for k in ("k1", "k2", "p1", "p2")]
        if prefix + "k3" in data:
            distortion.append(float(data[prefix + "k3"]))
        width = data.get("Camera.width", data.get("Camera1.width", 0))
        height = data.get("Camera.height", data.get("Camera1.height", 0))
    else:
        fx, fy, cx, cy = (_number(data, k, path) for k in ("fx", "fy", "cx", "cy"))
        distortion = _numbers(data.get("distortion", []) or [], "distortion", path)
        width, height = data.get("width", 0), data.get("height", 0)
    if not width or not height:
        if image_size is None:
            raise CalibrationError(path, "image size missing: add width and height")
        width, height = image_size
    try:
        width, height = int(width), int(height)
    except (TypeError, ValueError):
        raise CalibrationError(path, f"width/height must be integers, got {width!r}x{height!r}") from None
    if all(d == 0 for d in distortion):
        distortion = []
    return CameraIntrinsics(fx, fy, cx, cy, width, height, tuple(distortion), source=source)


def _exactly(values: list[float], n: int, key: str, path: Path) -> list[float]:
    if len(values) != n:
        raise CalibrationError(path, f"{key!r} must have {n} values, got {len(values)}")
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
