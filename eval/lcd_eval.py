"""``symbio eval lcd``: loop-closure precision/recall of one detector on any dataset with GT loops.

Keyframes are every frame at least ``--keyframe-period`` seconds after the previous keyframe
(default 0.2 s: every 6th frame at 30 Hz, every frame of a loop-pairs set, whose frames are 1 s
apart). Each keyframe gets ORB features and objects, then goes to the detector; its best candidate
is scored against the ground truth as described in ``eval.lcd_metrics``. Timing is per keyframe,
split into features, objects and the detector itself.
"""

from __future__ import annotations

import argparse
import csv
import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from eval.lcd_metrics import (
    gt_references,
    has_reachable_loop,
    is_true_match,
    precision_recall_curve,
    summarise,
)
from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.datasets import Dataset, open_dataset
from frontends.datasets.cli import add_dataset_arguments
from frontends.errors import ConfigError, SymbioError
from frontends.types import DetectedObject, Frame, Keyframe
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS, LoopDetector, ObjectDetector
from lcd.features import OrbConfig, extract_orb

log = logging.getLogger(__name__)


class DetectorFailure(SymbioError):
    """A loop detector raised while processing a keyframe."""


@dataclass
class QueryRecord:
    keyframe: int
    frame: int
    match_frame: int
    score: float
    correct: bool
    has_loop: bool
    ms_features: float
    ms_objects: float
    ms_detector: float


@dataclass
class LcdRun:
    records: list[QueryRecord] = field(default_factory=list)
    object_failures: int = 0
    keyframes: int = 0


def keyframes_of(dataset: Dataset, period: float) -> Iterator[Frame]:
    last = -np.inf
    for frame in dataset:
        if frame.timestamp - last >= period - 1e-9:
            last = frame.timestamp
            yield frame


def detect_objects(detector: ObjectDetector, frame: Frame, run: LcdRun) -> tuple[DetectedObject, ...]:
    """Objects of a frame; a failing object detector costs this keyframe its objects, not the run."""
    try:
        return tuple(detector.detect(frame.image, frame))
    except Exception as exc:  # plugin boundary: any detector error is isolated to its frame
        run.object_failures += 1
        log.warning(
            "object detector %s failed on %s: %s; keyframe kept without objects",
            detector.name,
            frame.path or f"frame {frame.index}",
            exc,
        )
        return ()


def run_lcd(
    dataset: Dataset,
    detector: LoopDetector,
    objects: ObjectDetector,
    orb: OrbConfig,
    keyframe_period: float,
    tolerance: int,
    progress: bool = True,
) -> LcdRun:
    pairs, _ = dataset.loop_pairs()
    if pairs is None:
        raise ConfigError(f"{dataset.root}: no ground-truth loops (no loop-pairs file and no GT poses)")
    references = gt_references(pairs)
    run = LcdRun()
    seen_frames: list[int] = []
    frames = keyframes_of(dataset, keyframe_period)
    for frame in tqdm(frames, disable=not progress, unit="kf", desc=f"lcd {detector.name}"):
        tick = time.perf_counter()
        keypoints, descriptors = extract_orb(frame.gray, orb)
        tock = time.perf_counter()
        found = detect_objects(objects, frame, run)
        tuck = time.perf_counter()
        pose = frame.gt_pose if frame.gt_pose is not None else np.eye(4)
        keyframe = Keyframe(
            run.keyframes, frame.index, frame.timestamp, pose, keypoints, descriptors, found, frame.image
        )
        try:
            candidates = detector.add(keyframe)
        except SymbioError:
            raise
        except Exception as exc:
            raise DetectorFailure(
                f"loop detector {detector.name!r} failed on keyframe {run.keyframes} "
                f"({frame.path or frame.index}): {exc!r}"
            ) from exc
        done = time.perf_counter()
        refs = references.get(frame.index)
        if candidates:
            best = candidates[0]
            match_frame = seen_frames[best.match]
            score, correct = float(best.score), is_true_match(match_frame, refs, tolerance)
        else:
            match_frame, score, correct = -1, float("-inf"), False
        # Which earlier keyframes the detector could have proposed: those outside its window.
        window = int(getattr(detector, "temporal_window", 0))
        eligible = seen_frames[: max(0, len(seen_frames) - window)]
        run.records.append(
            QueryRecord(
                run.keyframes,
                frame.index,
                match_frame,
                score,
                correct,
                has_reachable_loop(refs, eligible, tolerance),
                1e3 * (tock - tick),
                1e3 * (tuck - tock),
                1e3 * (done - tuck),
            )
        )
        seen_frames.append(frame.index)
        run.keyframes += 1
    return run


def figures_of(run: LcdRun, threshold: float) -> dict[str, Any]:
    records = run.records
    scores = np.array([r.score for r in records])
    correct = np.array([r.correct for r in records])
    figures: dict[str, Any] = dict(summarise(scores, correct, sum(r.has_loop for r in records), threshold))
    total = np.array([r.ms_features + r.ms_objects + r.ms_detector for r in records])
    for name, values in (
        ("ms_per_keyframe", total),
        ("ms_features", np.array([r.ms_features for r in records])),
        ("ms_objects", np.array([r.ms_objects for r in records])),
        ("ms_detector", np.array([r.ms_detector for r in records])),
    ):
        if len(values):
            figures[f"{name}_p50"] = float(np.percentile(values, 50))
            figures[f"{name}_p95"] = float(np.percentile(values, 95))
    figures["keyframes"] = run.keyframes
    figures["object_detector_failures"] = run.object_failures
    return figures


def write_queries_csv(path: Path, run: LcdRun) -> None:
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["keyframe", "frame", "match_frame", "score", "correct", "has_loop"])
        for r in run.records:
            writer.writerow(
                [r.keyframe, r.frame, r.match_frame, f"{r.score:.6f}", int(r.correct), int(r.has_loop)]
            )


def plot_pr(path: Path, run: LcdRun, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scores = np.array([r.score for r in run.records])
    correct = np.array([r.correct for r in run.records])
    _, precision, recall = precision_recall_curve(scores, correct, sum(r.has_loop for r in run.records))
    fig, ax = plt.subplots(figsize=(5, 4))
    ax.plot(recall, precision, drawstyle="steps-post")
    ax.set(xlabel="recall", ylabel="precision", xlim=(0, 1.02), ylim=(0, 1.02), title=title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def default_object_detector(dataset: Dataset) -> str:
    """Synthetic scenes carry their GT objects: use the oracle there, the CNN elsewhere."""
    return "oracle" if (dataset.root / "gt_objects.jsonl").is_file() else "ssd-mobilenet"


def add_lcd_parser(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "lcd",
        help="loop-closure precision/recall of a detector on a dataset with GT loops",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_dataset_arguments(parser)
    parser.add_argument(
        "--detector", default="symbiolcd2", help="loop detector name (see `symbio detectors`)"
    )
    parser.add_argument(
        "--object-detector", help="object detector (default: oracle on synthetic scenes, else ssd-mobilenet)"
    )
    parser.add_argument("--tolerance", type=int, default=0, help="frames a match may be off a GT reference")
    parser.add_argument("--keyframe-period", type=float, default=0.2, help="seconds between keyframes")
    parser.add_argument("--config", type=Path, help="YAML of the loop detector's config")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a loop-detector config value",
    )
    parser.add_argument(
        "--object-set",
        dest="object_overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override an object-detector config value",
    )
    parser.add_argument(
        "--orb-set",
        dest="orb_overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override an ORB config value",
    )
    parser.add_argument("--plot", type=Path, metavar="PNG", help="save the precision/recall curve")
    parser.add_argument("--csv", type=Path, help="save every query's best candidate")
    parser.add_argument("--no-progress", action="store_true")
    add_json_option(parser)
    parser.set_defaults(handler=run_lcd_command)


def run_lcd_command(args: argparse.Namespace) -> int:
    from frontends.config import load_config

    dataset = open_dataset(args.path, args.fmt, calib=args.calib, strict=args.strict)
    detector = LOOP_DETECTORS.load(args.detector)(args.overrides, args.config)
    object_name = args.object_detector or default_object_detector(dataset)
    objects = OBJECT_DETECTORS.load(object_name)(args.object_overrides)
    orb = load_config(OrbConfig, None, args.orb_overrides)
    run = run_lcd(dataset, detector, objects, orb, args.keyframe_period, args.tolerance, not args.no_progress)
    figures = {
        "detector": args.detector,
        "object_detector": object_name,
        "tolerance": args.tolerance,
        **figures_of(run, detector.threshold),
    }
    print(f"eval lcd: {args.detector} on {dataset.root} ({dataset.format_name}, {run.keyframes} keyframes)")
    print_figures(figures)
    if args.csv:
        write_queries_csv(args.csv, run)
    if args.plot:
        plot_pr(args.plot, run, f"{args.detector} on {dataset.root.name}")
    write_json(args.json, figures)
    return 0


def add_parser(subparsers: Any) -> None:
    evaluate = subparsers.add_parser("eval", help="evaluate loop detectors and SLAM runs")
    commands = evaluate.add_subparsers(dest="eval_command", metavar="SUBCOMMAND", required=True)
    add_lcd_parser(commands)
    detectors = subparsers.add_parser("detectors", help="list the installed loop and object detectors")
    detectors.set_defaults(handler=list_detectors)


def list_detectors(args: argparse.Namespace) -> int:
    for title, registry in (("loop detectors", LOOP_DETECTORS), ("object detectors", OBJECT_DETECTORS)):
        print(f"{title} (entry points: {registry.group}):")
        for name in registry.names():
            print(f"  {name:<22} {registry.origin(name)}")
    return 0
