"""``onnx``: any ONNX object detector with a declared output layout, run by onnxruntime.

``layout`` says how to feed the model and read its outputs:

* ``ssd-raw``: SSD-MobileNet-v2 COCO without post-processing (``ssd_mobilenet_v2_coco_raw.onnx`` of
  the shared models, see its README): input ``[1, 300, 300, 3]`` RGB scaled to [-1, 1]; outputs box
  codes ``[1, 1917, 1, 4]`` (ty, tx, th, tw) and sigmoid scores ``[1, 1917, 91]`` (column k = TF COCO
  id k, 0 = background). The 1917 anchors are generated as the TF-OD-API multiple-grid anchor
  generator of that model does (``ssd_anchors``), boxes decoded with the (10, 10, 5, 5) scales and
  post-processed like OpenCV's DetectionOutput layer of the ``ssd-mobilenet`` path: per class the
  100 best boxes above ``score_threshold`` enter NMS at IoU ``nms_threshold`` (0.6), then the
  ``max_detections`` (100) best overall. The image is resized with ``cv2.INTER_LINEAR`` exactly as
  ``cv2.dnn.blobFromImage`` does, so both paths see the same pixels and agree within 1 px / 0.01.
* ``maskrcnn``: the ONNX-model-zoo Mask R-CNN (MaskRCNN-10): input ``[3, H, W]`` BGR minus the
  Detectron means (102.9801, 115.9465, 122.7717), shorter side resized to ``input_size`` (800) and
  zero-padded to a multiple of 32; outputs boxes ``[N, 4]`` (resized-image pixels), labels ``[N]``
  (1-based COCO-80), scores ``[N]``, masks ``[N, 1, 28, 28]``. The model runs its own NMS, so only
  ``score_threshold`` and ``max_detections`` apply; each mask is resized into its box and
  thresholded at ``mask_threshold`` (0.5, as the zoo's demo), giving an image-sized boolean mask.
* ``yolo``: Ultralytics YOLOv5/v8 exports: input ``[1, 3, S, S]`` RGB / 255, letterboxed (aspect
  kept, grey 114 padding split evenly); output ``[1, 4 + C, A]`` (v8: cx, cy, w, h, class scores) or
  ``[1, A, 5 + C]`` (v5: objectness before the class scores; score = objectness x class score), told
  apart by the class count C. Each box keeps its best class; per-class NMS; the letterbox is undone.

Class names (``classes``): ``coco90`` (ssd-raw default), ``coco80+1`` (maskrcnn default), ``coco80``
(yolo default) or a text file with one name per line; model classes without a name are ignored.
``input_size`` 0 takes the side from the model's input shape (maskrcnn: 800). Errors of
onnxruntime (which raises its own exception types) are reported as ``ModelError`` naming the model.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import onnxruntime as ort

from frontends.config import load_config
from frontends.errors import ConfigError, ModelError
from frontends.types import DetectedObject, Frame
from lcd.objects.coco import class_names
from lcd.objects.ssd_cv2 import (
    DEFAULT_SCORE_THRESHOLD,
    SSD_MAX_DETECTIONS,
    SSD_NMS_THRESHOLD,
    SSD_PRE_NMS_TOP_K,
    ReloadedModel,
    check_post_processing,
    clip_box,
    pixel_box,
    prepare_image,
)

Layout = Literal["ssd-raw", "maskrcnn", "yolo"]
DEFAULT_CLASSES: dict[str, str] = {"ssd-raw": "coco90", "maskrcnn": "coco80+1", "yolo": "coco80"}
#: Shorter image side of the zoo's Mask R-CNN preprocessing.
MASKRCNN_SIZE = 800
MASKRCNN_MEAN_BGR = np.array([102.9801, 115.9465, 122.7717], np.float32)
MASKRCNN_PAD = 32
YOLO_PAD_VALUE = 114
#: Box-code scales of the SSD box coder (ty, tx, th, tw).
SSD_BOX_SCALES = np.array([10.0, 10.0, 5.0, 5.0])


@dataclass(frozen=True)
class OnnxConfig:
    #: The .onnx file (required).
    model: str = ""
    #: How the model is fed and read: ssd-raw, maskrcnn or yolo (see the module docstring).
    layout: Layout = "ssd-raw"
    #: Network input side (pixels); 0: from the model's input shape (maskrcnn: 800, the shorter side).
    input_size: int = 0
    #: ``coco90``, ``coco80``, ``coco80+1`` or a names file; empty: the layout's default.
    classes: str = ""
    #: Boxes must score above this to be reported.
    score_threshold: float = DEFAULT_SCORE_THRESHOLD
    #: IoU above which the lower-scored box of a class is suppressed (maskrcnn runs its own NMS).
    nms_threshold: float = SSD_NMS_THRESHOLD
    #: Most boxes reported per image, best first.
    max_detections: int = SSD_MAX_DETECTIONS
    #: Mask R-CNN: mask probability above which a pixel belongs to the object.
    mask_threshold: float = 0.5
    #: onnxruntime intra-op threads; 0 lets onnxruntime choose (all cores).
    threads: int = 2

    def __post_init__(self) -> None:
        check_post_processing("onnx detector", self.score_threshold, self.nms_threshold, self.max_detections)
        if self.input_size < 0 or self.threads < 0:
            raise ConfigError("onnx detector: input_size and threads must be >= 0")
        if not 0.0 < self.mask_threshold < 1.0:
            raise ConfigError(f"onnx detector: mask_threshold must be in (0, 1), got {self.mask_threshold}")


class OnnxDetector(ReloadedModel):
    """One ONNX model and its layout; the onnxruntime session is created once per instance."""

    name = "onnx"

    def __init__(self, config: OnnxConfig) -> None:
        self.config = config
        # Checked here, not in the config: load_config builds the defaults first.
        if not config.model:
            raise ConfigError("onnx detector: set model=PATH to the .onnx file")
        self.model_path = Path(config.model)
        if not self.model_path.is_file():
            raise ModelError(self.model_path, "ONNX model file not found")
        self.classes = class_names(config.classes, DEFAULT_CLASSES[config.layout])
        options = ort.SessionOptions()
        options.intra_op_num_threads = config.threads
        options.inter_op_num_threads = 1
        try:
            self._session = ort.InferenceSession(
                str(self.model_path), options, providers=["CPUExecutionProvider"]
            )
        except Exception as exc:  # onnxruntime's exception types derive from Exception only
            raise ModelError(self.model_path, f"onnxruntime cannot load the model ({exc})") from None
        inputs = self._session.get_inputs()
        if len(inputs) != 1:
            raise ModelError(self.model_path, f"expected one input, the model has {len(inputs)}")
        self._input = inputs[0].name
        self.input_size = config.input_size or self._declared_size(inputs[0].shape)
        if config.layout == "ssd-raw":
            self._anchors = ssd_anchors()

    def _declared_size(self, shape: Sequence[Any]) -> int:
        layout = self.config.layout
        if layout == "maskrcnn":
            return MASKRCNN_SIZE
        expected = {"ssd-raw": "[1, S, S, 3]", "yolo": "[1, 3, S, S]"}[layout]
        sides = list(shape[1:3]) if layout == "ssd-raw" else list(shape[2:4])
        if len(shape) != 4 or not all(isinstance(s, int) and s > 0 for s in sides) or sides[0] != sides[1]:
            raise ModelError(
                self.model_path,
                f"layout {layout} expects an input {expected} with a fixed side S, got {list(shape)}; "
                "set input_size for a dynamic input",
            )
        return int(sides[0])

    def detect(self, image: np.ndarray, frame: Frame | None = None) -> list[DetectedObject]:
        bgr = prepare_image(image, self.name)
        if bgr is None:
            return []
        if self.config.layout == "ssd-raw":
            return self._detect_ssd(bgr)
        if self.config.layout == "maskrcnn":
            return self._detect_maskrcnn(bgr)
        return self._detect_yolo(bgr)

    def _run(self, tensor: np.ndarray) -> list[np.ndarray]:
        try:
            outputs = self._session.run(None, {self._input: tensor})
        except Exception as exc:  # onnxruntime's exception types derive from Exception only
            raise ModelError(self.model_path, f"onnxruntime failed ({exc})") from None
        return [np.asarray(out) for out in outputs]

    def _yolo_rows(self, outputs: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Rows (cx, cy, w, h, ...) and their class scores, from a v8 or v5 output."""
        count = max(self.classes) + 1
        shape = outputs[0].shape if outputs else ()
        if len(shape) == 3 and shape[0] == 1:
            out = outputs[0][0]
            if out.shape[1] == count + 5:
                return out, out[:, 5:] * out[:, 4:5]
            if out.shape[0] == count + 4:
                return out.T, out.T[:, 4:]
            if out.shape[1] == count + 4:
                return out, out[:, 4:]
        raise self._unexpected(
            f"[1, {count + 4}, A] (v8) or [1, A, {count + 5}] (v5) for {count} classes", outputs
        )

    def _unexpected(self, what: str, outputs: Sequence[np.ndarray]) -> ModelError:
        shapes = [list(out.shape) for out in outputs]
        return ModelError(self.model_path, f"layout {self.config.layout}: expected {what}, got {shapes}")

    def _detect_ssd(self, bgr: np.ndarray) -> list[DetectedObject]:
        size = self.input_size
        # The same resize and channel order as cv2.dnn.blobFromImage(..., swapRB=True) on the cv2 path.
        rgb = cv2.cvtColor(cv2.resize(bgr, (size, size), interpolation=cv2.INTER_LINEAR), cv2.COLOR_BGR2RGB)
        tensor = (rgb.astype(np.float32) * np.float32(2.0 / 255.0) - np.float32(1.0))[None]
        outputs = self._run(tensor)
        anchors = len(self._anchors)
        if not (len(outputs) == 2 and outputs[0].size == anchors * 4 and outputs[1].ndim == 3):
            raise self._unexpected(
                f"box codes [1, {anchors}, 1, 4] and scores [1, {anchors}, classes]", outputs
            )
        boxes = decode_ssd_boxes(outputs[0].reshape(-1, 4), self._anchors)
        scores = outputs[1].reshape(anchors, -1)
        anchor_ids, class_ids = np.nonzero(scores > self.config.score_threshold)
        named = np.isin(class_ids, list(self.classes))
        anchor_ids, class_ids = anchor_ids[named], class_ids[named]
        keep = batched_nms(
            boxes[anchor_ids],
            scores[anchor_ids, class_ids],
            class_ids,
            self.config,
            pre_nms_top_k=SSD_PRE_NMS_TOP_K,
        )
        height, width = bgr.shape[:2]
        objects = []
        for k in keep:
            box = pixel_box(boxes[anchor_ids[k]], width, height)
            if box is not None:
                score = float(scores[anchor_ids[k], class_ids[k]])
                objects.append(DetectedObject(self.classes[int(class_ids[k])], score, box))
        return objects

    def _detect_maskrcnn(self, bgr: np.ndarray) -> list[DetectedObject]:
        height, width = bgr.shape[:2]
        ratio = self.input_size / min(height, width)
        resized = cv2.resize(bgr, (int(ratio * width), int(ratio * height)), interpolation=cv2.INTER_LINEAR)
        padded_h = math.ceil(resized.shape[0] / MASKRCNN_PAD) * MASKRCNN_PAD
        padded_w = math.ceil(resized.shape[1] / MASKRCNN_PAD) * MASKRCNN_PAD
        tensor = np.zeros((3, padded_h, padded_w), np.float32)
        tensor[:, : resized.shape[0], : resized.shape[1]] = (resized - MASKRCNN_MEAN_BGR).transpose(2, 0, 1)
        outputs = self._run(tensor)
        if not (
            len(outputs) == 4
            and outputs[0].ndim == 2
            and outputs[0].shape[1] == 4
            and outputs[1].shape == outputs[2].shape == (outputs[0].shape[0],)
            and outputs[3].ndim == 4
            and outputs[3].shape[:2] == (outputs[0].shape[0], 1)
        ):
            raise self._unexpected("boxes [N, 4], labels [N], scores [N], masks [N, 1, h, w]", outputs)
        boxes, labels, scores, masks = outputs
        order = np.argsort(-scores, kind="stable")
        objects: list[DetectedObject] = []
        for k in order:
            label = self.classes.get(int(labels[k]))
            if scores[k] <= self.config.score_threshold or label is None:
                continue
            box = clip_box(boxes[k] / ratio, width, height)
            if box is None:
                continue
            mask = paste_mask(masks[k, 0], box, width, height, self.config.mask_threshold)
            objects.append(DetectedObject(label, float(scores[k]), box, mask=mask))
            if len(objects) == self.config.max_detections:
                break
        return objects

    def _detect_yolo(self, bgr: np.ndarray) -> list[DetectedObject]:
        size = self.input_size
        height, width = bgr.shape[:2]
        scale = min(size / height, size / width)
        new_w, new_h = round(width * scale), round(height * scale)
        # Ultralytics' letterbox: the padding split in two, the odd pixel going right/bottom.
        left, top = round((size - new_w) / 2 - 0.1), round((size - new_h) / 2 - 0.1)
        canvas = np.full((size, size, 3), YOLO_PAD_VALUE, np.uint8)
        canvas[top : top + new_h, left : left + new_w] = cv2.resize(
            bgr, (new_w, new_h), interpolation=cv2.INTER_LINEAR
        )
        tensor = cv2.cvtColor(canvas, cv2.COLOR_BGR2RGB).transpose(2, 0, 1)[None].astype(np.float32) / 255
        outputs = self._run(np.ascontiguousarray(tensor))
        rows, class_scores = self._yolo_rows(outputs)
        class_ids = np.argmax(class_scores, axis=1)
        scores = class_scores[np.arange(len(rows)), class_ids]
        named = np.isin(class_ids, list(self.classes))
        candidates = np.nonzero((scores > self.config.score_threshold) & named)[0]
        cx, cy, w, h = rows[candidates, :4].T
        corners = np.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], axis=1)
        keep = batched_nms(corners, scores[candidates], class_ids[candidates], self.config)
        objects = []
        for k in keep:
            x0, y0, x1, y1 = corners[k]
            box = clip_box(
                ((x0 - left) / scale, (y0 - top) / scale, (x1 - left) / scale, (y1 - top) / scale),
                width,
                height,
            )
            if box is not None:
                label = self.classes[int(class_ids[candidates[k]])]
                objects.append(DetectedObject(label, float(scores[candidates[k]]), box))
        return objects


def create(overrides: Sequence[str] = (), config_path: Any = None) -> OnnxDetector:
    return OnnxDetector(load_config(OnnxConfig, config_path, overrides))


def ssd_anchors(
    feature_maps: Sequence[int] = (19, 10, 5, 3, 2, 1),
    min_scale: float = 0.2,
    max_scale: float = 0.95,
    aspect_ratios: Sequence[float] = (1.0, 2.0, 0.5, 3.0, 0.3333),
) -> np.ndarray:
    """(N, 4) anchors (yc, xc, h, w), normalised, in the order of the SSD box predictor outputs.

    The TF-OD-API ``multiple_grid_anchor_generator`` (``ssd_anchor_generator`` in the model's
    pipeline.config, whose aspect ratio 1/3 is written 0.3333): scales evenly spaced from
    ``min_scale`` to ``max_scale`` plus 1.0; on the first map the reduced set (0.1, 1), (s0, 2),
    (s0, 0.5); on the others every aspect ratio at s_k plus an aspect-1 box at sqrt(s_k * s_k+1).
    Height = s / sqrt(a), width = s * sqrt(a); centres at (i + 0.5) / map size; order: row, column,
    box. (OpenCV's text graph uses 0.333, a 0.05 % larger box for that ratio; well under 1 px.)
    """
    count = len(feature_maps)
    scales = [min_scale + (max_scale - min_scale) * k / (count - 1) for k in range(count)] + [1.0]
    layers = []
    for k, cells in enumerate(feature_maps):
        if k == 0:
            specs = [(0.1, 1.0), (scales[0], 2.0), (scales[0], 0.5)]
        else:
            specs = [(scales[k], a) for a in aspect_ratios] + [(math.sqrt(scales[k] * scales[k + 1]), 1.0)]
        sizes = np.array([(s / math.sqrt(a), s * math.sqrt(a)) for s, a in specs])
        centres = (np.arange(cells) + 0.5) / cells
        yc, xc = np.meshgrid(centres, centres, indexing="ij")
        layer = np.empty((cells, cells, len(specs), 4))
        layer[..., 0], layer[..., 1] = yc[..., None], xc[..., None]
        layer[..., 2], layer[..., 3] = sizes[:, 0], sizes[:, 1]
        layers.append(layer.reshape(-1, 4))
    return np.concatenate(layers)


def decode_ssd_boxes(codes: np.ndarray, anchors: np.ndarray) -> np.ndarray:
    """Box codes (ty, tx, th, tw) and anchors (yc, xc, h, w) -> boxes (x0, y0, x1, y1), normalised."""
    ty, tx, th, tw = (codes.astype(np.float64) / SSD_BOX_SCALES).T
    ya, xa, ha, wa = anchors.T
    yc, xc = ty * ha + ya, tx * wa + xa
    h, w = np.exp(th) * ha, np.exp(tw) * wa
    return np.stack([xc - w / 2, yc - h / 2, xc + w / 2, yc + h / 2], axis=1)


def batched_nms(
    corners: np.ndarray,
    scores: np.ndarray,
    class_ids: np.ndarray,
    config: OnnxConfig,
    pre_nms_top_k: int = 0,
) -> list[int]:
    """Per-class greedy NMS; indices of the kept boxes, best first, at most ``max_detections``.

    ``pre_nms_top_k`` > 0 keeps only each class's best boxes before NMS (the DetectionOutput ``top_k``).
    """
    if len(scores) == 0:
        return []
    candidates = np.arange(len(scores))
    if pre_nms_top_k > 0:
        order = np.lexsort((-scores, class_ids))
        first = np.searchsorted(class_ids[order], class_ids[order], side="left")
        candidates = np.sort(order[np.arange(len(order)) - first < pre_nms_top_k])
    xywh = np.column_stack([corners[:, :2], corners[:, 2:] - corners[:, :2]])[candidates]
    picked = cv2.dnn.NMSBoxesBatched(
        xywh.tolist(), scores[candidates].tolist(), class_ids[candidates].tolist(), 0.0, config.nms_threshold
    )
    kept = candidates[np.asarray(picked, dtype=np.int64).reshape(-1)]
    kept = kept[np.argsort(-scores[kept], kind="stable")]
    return [int(k) for k in kept[: config.max_detections]]


def paste_mask(
    mask: np.ndarray, box: tuple[float, float, float, float], width: int, height: int, threshold: float
) -> np.ndarray:
    """A low-resolution mask of the box -> an image-sized boolean mask (the zoo's paste)."""
    x0, y0 = int(box[0]), int(box[1])
    x1, y1 = max(x0 + 1, math.ceil(box[2])), max(y0 + 1, math.ceil(box[3]))
    resized = cv2.resize(mask.astype(np.float32), (x1 - x0, y1 - y0), interpolation=cv2.INTER_LINEAR)
    full = np.zeros((height, width), dtype=bool)
    full[y0:y1, x0:x1] = resized[: height - y0, : width - x0] > threshold
    return full
