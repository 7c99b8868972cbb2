"""COCO class names in the two numberings detectors use.

* ``COCO90``: the TF Object Detection API label map (``mscoco_label_map.pbtxt``), ids 1..90 of which
  80 are used (12, 26, 29, 30, 45, 66, 68, 69, 71 and 83 are not). SSD-MobileNet-v2 (both the OpenCV
  and the raw ONNX path) reports these ids; score column k of the raw model is id k, column 0 the
  background.
* ``COCO80``: the same 80 names contiguously in id order, the list YOLO exports index from 0 and the
  ONNX-zoo Mask R-CNN from 1.

Names follow the COCO 2017 spelling (``tv``, ``couch``, ``potted plant``, ``dining table``), which is
also what the synthetic scenes use, so ground truth and CNN labels compare directly.
"""

from __future__ import annotations

from pathlib import Path

from frontends.errors import InputFileError

COCO90: dict[int, str] = {
    1: "person",
    2: "bicycle",
    3: "car",
    4: "motorcycle",
    5: "airplane",
    6: "bus",
    7: "train",
    8: "truck",
    9: "boat",
    10: "traffic light",
    11: "fire hydrant",
    13: "stop sign",
    14: "parking meter",
    15: "bench",
    16: "bird",
    17: "cat",
    18: "dog",
    19: "horse",
    20: "sheep",
    21: "cow",
    22: "elephant",
    23: "bear",
    24: "zebra",
    25: "giraffe",
    27: "backpack",
    28: "umbrella",
    31: "handbag",
    32: "tie",
    33: "suitcase",
    34: "frisbee",
    35: "skis",
    36: "snowboard",
    37: "sports ball",
    38: "kite",
    39: "baseball bat",
    40: "baseball glove",
    41: "skateboard",
    42: "surfboard",
    43: "tennis racket",
    44: "bottle",
    46: "wine glass",
    47: "cup",
    48: "fork",
    49: "knife",
    50: "spoon",
    51: "bowl",
    52: "banana",
    53: "apple",
    54: "sandwich",
    55: "orange",
    56: "broccoli",
    57: "carrot",
    58: "hot dog",
    59: "pizza",
    60: "donut",
    61: "cake",
    62: "chair",
    63: "couch",
    64: "potted plant",
    65: "bed",
    67: "dining table",
    70: "toilet",
    72: "tv",
    73: "laptop",
    74: "mouse",
    75: "remote",
    76: "keyboard",
    77: "cell phone",
    78: "microwave",
    79: "oven",
    80: "toaster",
    81: "sink",
    82: "refrigerator",
    84: "book",
    85: "clock",
    86: "vase",
    87: "scissors",
    88: "teddy bear",
    89: "hair drier",
    90: "toothbrush",
}

COCO80: tuple[str, ...] = tuple(COCO90[k] for k in sorted(COCO90))


def class_names(source: str, default: str) -> dict[int, str]:
    """Model class index -> name: ``coco90``, ``coco80`` (index 0 first), ``coco80+1`` (index 1 first),
    or a text file with one name per line (index 0 first; empty lines keep their index unused).

    ``source`` empty means ``default``.
    """
    source = source or default
    if source == "coco90":
        return dict(COCO90)
    if source == "coco80":
        return dict(enumerate(COCO80))
    if source == "coco80+1":
        return {k + 1: name for k, name in enumerate(COCO80)}
    path = Path(source)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(
            path, f"cannot read class names ({exc}); use coco90, coco80, coco80+1 or a file"
        ) from None
    names = {k: line.strip() for k, line in enumerate(lines) if line.strip()}
    if not names:
        raise InputFileError(path, "no class names in file (expected one name per line)")
    return names
