"""The swappable parts of loop-closure detection: loop detectors and object detectors.

A loop detector consumes keyframes one by one and answers each with scored candidates among the
keyframes it has seen before; an object detector turns an image into labelled boxes. Both are
looked up by name in a registry that other packages extend through entry points
(``symbio.loop_detectors``, ``symbio.object_detectors``).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from frontends.registry import Registry
from frontends.types import DetectedObject, Frame, Keyframe


@dataclass(frozen=True)
class LoopCandidate:
    """A proposed revisit: keyframe ``query`` sees the place of the earlier keyframe ``match``."""

    query: int
    match: int
    #: The detector's score; higher is more likely a loop. Thresholds apply to this value.
    score: float
    #: The parts the score is made of (e.g. ``wl``, ``temporal``, ``vbow``), for reports and ablations.
    components: Mapping[str, float] = field(default_factory=dict)


@runtime_checkable
class LoopDetector(Protocol):
    """Consumes keyframes in order; returns candidates against earlier keyframes, best first.

    ``keyframe.id`` values increase. A detector never proposes a keyframe inside its own temporal
    window of the query. ``threshold`` is the score at or above which a candidate counts as a loop.
    A detector may also have ``proposal_threshold``, the lowest score a SLAM run checks geometrically;
    without it the run checks scores from ``loop_closing.proposal_ratio`` x ``threshold`` up, and
    ``release()``, which a SLAM run calls once the stream has ended (before its end-of-run bundle
    adjustment) to free the keyframe database; ``add`` is not called after it.
    """

    name: str
    threshold: float

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]: ...


@runtime_checkable
class ObjectDetector(Protocol):
    """``detect`` returns the objects in a BGR (or grey) image; an empty list when there are none.

    ``frame`` is the frame the image belongs to; CNN detectors ignore it, the ground-truth oracle of
    synthetic scenes uses its index and path to look the objects up.
    """

    name: str

    def detect(self, image: np.ndarray, frame: Frame | None = None) -> list[DetectedObject]: ...


#: A factory builds a detector from ``--set key=value`` overrides and an optional YAML file.
class LoopDetectorFactory(Protocol):
    def __call__(self, overrides: Sequence[str] = (), config_path: Any = None) -> LoopDetector: ...


class ObjectDetectorFactory(Protocol):
    def __call__(self, overrides: Sequence[str] = (), config_path: Any = None) -> ObjectDetector: ...


LOOP_DETECTORS: Registry[LoopDetectorFactory] = Registry(
    "loop detector",
    "symbio.loop_detectors",
    {
        "vbow": "lcd.vbow:create",
        "symbiolcd": "lcd.symbiolcd:create",
        "symbiolcd2": "lcd.symbiolcd2:create",
        "symbiolcd2-flat": "lcd.symbiolcd2:create_flat",
        "symbiolcd2-two-tier": "lcd.symbiolcd2:create_two_tier",
    },
)

OBJECT_DETECTORS: Registry[ObjectDetectorFactory] = Registry(
    "object detector",
    "symbio.object_detectors",
    {
        "ssd-mobilenet": "lcd.objects.ssd_cv2:create",
        "onnx": "lcd.objects.onnx:create",
        "oracle": "lcd.objects.oracle:create",
        "none": "lcd.objects.filtering:create_none",
    },
)
