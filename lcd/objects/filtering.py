"""The paper's object filter (SymbioLCD2 III-B), and ``none``, the detector that finds nothing.

"Any objects with labels that correspond to movable entities, e.g. person, car or bicycles, are
filtered out. [...] Additionally, any objects that are too large and overlap with other objects in
the scene are also filtered out." ``filter_objects`` applies, in this order:

1. ``min_score`` (0.3): weaker objects are dropped. It equals the detectors' default threshold, so a
   detector run lower (e.g. for precision-recall curves) still feeds the graph the same objects.
2. ``movable_labels``: the COCO classes that move on their own or are moved around as a whole:
   people, vehicles (bicycle, car, motorcycle, bus, train, truck, boat) and animals (bird, cat, dog,
   horse, sheep, cow, elephant, bear, zebra, giraffe). Airplanes are left in (they stand still in
   the scenes a SLAM camera sees, and models show them, e.g. in an office).
3. ``max_area_fraction`` (0.5): a box covering more than half the image is dropped; such boxes are
   whole-scene false positives (a "dining table" for the desk plane) or objects so close that
   they anchor no place.
4. Overlap: when a box lies mostly inside another (intersection over the smaller box's area above
   ``max_overlap``, 0.8), the larger one is dropped: it is the container (the table under the cups)
   or a duplicate detection, and keeping the smaller one keeps the finer anchor. Boxes are visited
   from the smallest up (ties: higher score first), each compared with the boxes already kept.

Survivors keep their input order. ``create_none`` (``none`` in the registry) is the detector that
returns no objects, for vBoW-only runs and ablations.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from frontends.config import load_config
from frontends.errors import ConfigError
from frontends.types import DetectedObject, Frame

MOVABLE_LABELS: tuple[str, ...] = (
    "person",
    "bicycle",
    "car",
    "motorcycle",
    "bus",
    "train",
    "truck",
    "boat",
    "bird",
    "cat",
    "dog",
    "horse",
    "sheep",
    "cow",
    "elephant",
    "bear",
    "zebra",
    "giraffe",
)
#: The movable classes that are often parked: a frontend may keep one it sees standing still.
VEHICLE_LABELS: tuple[str, ...] = ("bicycle", "car", "motorcycle", "bus", "train", "truck", "boat")
#: People and animals: they stand still only for moments, so two visits of a place never see them
#: in the same spot (what the loop verifier leaves out, ``slam_backend.verify``).
WALKING_LABELS: tuple[str, ...] = tuple(label for label in MOVABLE_LABELS if label not in VEHICLE_LABELS)


@dataclass(frozen=True)
class FilterConfig:
    #: Objects scoring below this are dropped (the detectors' default threshold).
    min_score: float = 0.3
    #: Classes dropped as movable: COCO's people, vehicles and animals (airplanes are kept).
    movable_labels: tuple[str, ...] = MOVABLE_LABELS
    #: Largest box area as a fraction of the image area.
    max_area_fraction: float = 0.5
    #: Intersection over the smaller box's area above which the larger of two boxes is dropped.
    max_overlap: float = 0.8

    def __post_init__(self) -> None:
        if not 0.0 < self.max_area_fraction <= 1.0:
            raise ConfigError(
                f"object filter: max_area_fraction must be in (0, 1], got {self.max_area_fraction}"
            )
        if not 0.0 < self.max_overlap <= 1.0:
            raise ConfigError(f"object filter: max_overlap must be in (0, 1], got {self.max_overlap}")


def filter_objects(
    objects: Sequence[DetectedObject], image_size: tuple[int, int], config: FilterConfig = FilterConfig()
) -> list[DetectedObject]:
    """The objects of an image of ``image_size`` (width, height) that SymbioLCD2 anchors on."""
    width, height = image_size
    movable = set(config.movable_labels)
    candidates = [
        k
        for k, obj in enumerate(objects)
        if obj.score >= config.min_score
        and obj.label not in movable
        and box_area(obj.box) <= config.max_area_fraction * width * height
    ]
    candidates.sort(key=lambda k: (box_area(objects[k].box), -objects[k].score))
    kept: list[int] = []
    for k in candidates:
        if all(intersection_over_smaller(objects[k].box, objects[j].box) <= config.max_overlap for j in kept):
            kept.append(k)
    return [objects[k] for k in sorted(kept)]


def box_area(box: Sequence[float]) -> float:
    return max(0.0, box[2] - box[0]) * max(0.0, box[3] - box[1])


def intersection_over_smaller(a: Sequence[float], b: Sequence[float]) -> float:
    inter = box_area((max(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), min(a[3], b[3])))
    smaller = min(box_area(a), box_area(b))
    return inter / smaller if smaller > 0 else 0.0


@dataclass(frozen=True)
class NoneConfig:
    """The ``none`` detector has no settings; an empty config still rejects unknown keys."""


class NoObjects:
    name = "none"

    def detect(self, image: np.ndarray, frame: Frame | None = None) -> list[DetectedObject]:
        return []


def create_none(overrides: Sequence[str] = (), config_path: Any = None) -> NoObjects:
    load_config(NoneConfig, config_path, overrides)
    return NoObjects()
