"""``oracle``: the ground-truth objects of a synthetic scene, optionally degraded like a real detector.

Objects come from the scene's ``gt_objects.jsonl`` (``frontends.synth.writer``): by default the file
next to the frame's ``rgb/`` folder (the grandparent of ``frame.path``), or ``objects_file``; the
frame is looked up by ``frame.index``. Each file is read once per detector instance.

Degradations, applied per object in file order:

* ``min_visible_fraction``: objects less visible than this are not reported.
* ``miss_rate``: probability that an object is not reported.
* ``flip_rate``: probability that a static object is reported as another label of the scene (uniform
  over the other static labels in the file). Movable objects keep their label ("person") so the
  object filter still drops them: ``DetectedObject`` has no movable flag.
* ``box_jitter``: standard deviation (px) of Gaussian noise added to each box coordinate; boxes are
  then clipped to the image, and a box that collapses is not reported.

All randomness comes from ``np.random.default_rng([seed, frame.index])`` and every object always
draws the same numbers (miss, flip, new label, four jitters), so a frame's result does not depend on
the call order, and changing one rate does not reshuffle the other degradations. Reported objects
have score 1.0 and keep their instance id and visible fraction.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from frontends.config import load_config
from frontends.errors import ConfigError, InputFileError
from frontends.types import DetectedObject, Frame
from lcd.objects.ssd_cv2 import clip_box

OBJECTS_FILE = "gt_objects.jsonl"


@dataclass(frozen=True)
class OracleConfig:
    #: The scene's gt_objects.jsonl; empty: ``<frame.path>/../../gt_objects.jsonl``.
    objects_file: str = ""
    #: Probability that an object is not reported.
    miss_rate: float = 0.0
    #: Probability that a static object is reported as another static label of the scene.
    flip_rate: float = 0.0
    #: Standard deviation of the box noise (pixels).
    box_jitter: float = 0.0
    #: Objects with a smaller visible fraction than this are not reported.
    min_visible_fraction: float = 0.0
    #: Seed of the degradations, mixed with the frame index.
    seed: int = 0

    def __post_init__(self) -> None:
        rates = {"miss_rate": self.miss_rate, "flip_rate": self.flip_rate}
        rates["min_visible_fraction"] = self.min_visible_fraction
        for key, value in rates.items():
            if not 0.0 <= value <= 1.0:
                raise ConfigError(f"oracle: {key} must be in [0, 1], got {value}")
        if self.box_jitter < 0:
            raise ConfigError(f"oracle: box_jitter must be >= 0, got {self.box_jitter}")


@dataclass(frozen=True)
class _GtObject:
    label: str
    instance: int
    box: tuple[float, float, float, float]
    visible_fraction: float
    movable: bool


@dataclass(frozen=True)
class _Scene:
    frames: dict[int, tuple[_GtObject, ...]]
    #: Sorted static labels: the choices of a label flip.
    static_labels: tuple[str, ...]


class OracleDetector:
    name = "oracle"

    def __init__(self, config: OracleConfig) -> None:
        self.config = config
        self._scenes: dict[Path, _Scene] = {}

    def detect(self, image: np.ndarray, frame: Frame | None = None) -> list[DetectedObject]:
        if frame is None:
            raise ConfigError(
                "the oracle object detector needs the frames of a synthetic scene (their index and path) "
                "to look up the ground-truth objects; use a CNN detector for plain images"
            )
        path = self._objects_path(frame)
        scene = self._scene(path)
        if frame.index not in scene.frames:
            raise InputFileError(path, f"no objects line for frame {frame.index}")
        config = self.config
        height, width = image.shape[:2]
        rng = np.random.default_rng([config.seed, frame.index])
        objects = []
        for gt in scene.frames[frame.index]:
            miss, flip = rng.random(2)
            choice = int(rng.integers(0, 1 << 30))
            noise = rng.normal(0.0, 1.0, 4) * config.box_jitter
            if gt.visible_fraction < config.min_visible_fraction or miss < config.miss_rate:
                continue
            label = gt.label
            others = [other for other in scene.static_labels if other != label]
            if not gt.movable and others and flip < config.flip_rate:
                label = others[choice % len(others)]
            box = clip_box((np.add(gt.box, noise)).tolist(), width, height)
            if box is not None:
                objects.append(
                    DetectedObject(
                        label, 1.0, box, instance=gt.instance, visible_fraction=gt.visible_fraction
                    )
                )
        return objects

    def _objects_path(self, frame: Frame) -> Path:
        if self.config.objects_file:
            return Path(self.config.objects_file)
        if frame.path is None:
            raise ConfigError(
                f"oracle: frame {frame.index} has no file path; "
                f"set objects_file to the scene's {OBJECTS_FILE}"
            )
        return Path(frame.path).parent.parent / OBJECTS_FILE

    def _scene(self, path: Path) -> _Scene:
        if path not in self._scenes:
            self._scenes[path] = _read_objects(path)
        return self._scenes[path]


def create(overrides: Sequence[str] = (), config_path: Any = None) -> OracleDetector:
    return OracleDetector(load_config(OracleConfig, config_path, overrides))


def _read_objects(path: Path) -> _Scene:
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(
            path, f"cannot read the ground-truth objects ({exc}); the oracle needs a synthetic scene"
        ) from None
    frames: dict[int, tuple[_GtObject, ...]] = {}
    labels: set[str] = set()
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
            objects = tuple(
                _GtObject(
                    str(item["label"]),
                    int(item["instance"]),
                    (
                        float(item["box"][0]),
                        float(item["box"][1]),
                        float(item["box"][2]),
                        float(item["box"][3]),
                    ),
                    float(item["visible_fraction"]),
                    bool(item["movable"]),
                )
                for item in record["objects"]
            )
            frames[int(record["frame"])] = objects
        except (ValueError, KeyError, TypeError, IndexError) as exc:
            raise InputFileError(
                path, f"malformed objects line ({type(exc).__name__}: {exc})", number
            ) from None
        labels.update(obj.label for obj in objects if not obj.movable)
    return _Scene(frames, tuple(sorted(labels)))
