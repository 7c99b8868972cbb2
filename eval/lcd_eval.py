"""``symbio eval lcd``: loop-closure precision/recall of one detector on any dataset with GT loops.

Keyframes are every frame at least ``--keyframe-period`` seconds after the previous keyframe
(default 0.2 s: every 6th frame at 30 Hz, every frame of a loop-pairs set, whose frames are 1 s
apart). Each keyframe gets ORB features and objects, then goes to the detector; its best candidate
is scored against the ground truth as described in ``eval.lcd_metrics``. Timing is per keyframe,
split into features, objects and the detector itself.

Several detectors (``--detector a,b,c``) share one pass: every keyframe's features and objects are
computed once and fed to each, so they are compared on identical inputs (the ablation table).
A detector or object detector that raises costs only that keyframe (logged and counted in
``loop_detector_failures`` / ``object_detector_failures``), never the run.
"""

from __future__ import annotations

import argparse
import csv
import logging
import time
from collections.abc import Sequence
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
from frontends.datasets.base import every_period
from frontends.datasets.cli import add_dataset_arguments
from frontends.errors import ConfigError
from frontends.types import DetectedObject, Frame, Keyframe
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS, LoopCandidate, LoopDetector, ObjectDetector
from lcd.features import OrbConfig, extract_orb

log = logging.getLogger(__name__)


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
    loop_detector_failures: int = 0
    keyframes: int = 0


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


def propose_loops(
    detector: LoopDetector, keyframe: Keyframe, frame: Frame, run: LcdRun
) -> list[LoopCandidate]:
    """A failing loop detector costs this query its candidates, not the run (counted and logged)."""
    try:
        return detector.add(keyframe)
    except Exception as exc:  # plugin boundary, like object detectors
        run.loop_detector_failures += 1
        log.warning(
            "loop detector %s failed on keyframe %d (%s): %r; the query counts as unanswered",
            detector.name,
            keyframe.id,
            frame.path or f"frame {frame.index}",
            exc,
        )
        return []


def run_lcd(
    dataset: Dataset,
    detectors: Sequence[LoopDetector],
    objects: ObjectDetector,
    orb: OrbConfig,
    keyframe_period: float,
    tolerance: int,
    progress: bool = True,
) -> list[LcdRun]:
    """One run per detector; every keyframe's features and objects are computed once for all."""
    pairs, _ = dataset.loop_pairs()
    if pairs is None:
        raise ConfigError(f"{dataset.root}: no ground-truth loops (no loop-pairs file and no GT poses)")
    references = gt_references(pairs)
    runs = [LcdRun() for _ in detectors]
    object_failures = LcdRun()
    seen_frames: list[int] = []
    names = ",".join(d.name for d in detectors)
    for frame in tqdm(
        every_period(dataset, keyframe_period), disable=not progress, unit="kf", desc=f"lcd {names}"
    ):
        tick = time.perf_counter()
        keypoints, descriptors = extract_orb(frame.gray, orb)
        tock = time.perf_counter()
        found = detect_objects(objects, frame, object_failures)
        tuck = time.perf_counter()
        pose = frame.gt_pose if frame.gt_pose is not None else np.eye(4)
        keyframe = Keyframe(
            len(seen_frames), frame.index, frame.timestamp, pose, keypoints, descriptors, found, frame.image
        )
        refs = references.get(frame.index)
        for detector, run in zip(detectors, runs, strict=True):
            start = time.perf_counter()
            candidates = propose_loops(detector, keyframe, frame, run)
            done = time.perf_counter()
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
                    keyframe.id,
                    frame.index,
                    match_frame,
                    score,
                    correct,
                    has_reachable_loop(refs, eligible, tolerance),
                    1e3 * (tock - tick),
                    1e3 * (tuck - tock),
                    1e3 * (done - start),
                )
            )
            run.keyframes += 1
            run.object_failures = object_failures.object_failures
        seen_frames.append(frame.index)
    return runs


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
    figures["loop_detector_failures"] = run.loop_detector_failures
    return figures


#: Counters a detector may expose, reported with its figures (e.g. SymbioLCD2's keyframes with too
#: few objects for the paper's graph).
DETECTOR_COUNTERS = ("object_poor_keyframes",)


def detector_counters(detector: LoopDetector) -> dict[str, int]:
    return {name: int(getattr(detector, name)) for name in DETECTOR_COUNTERS if hasattr(detector, name)}


def write_queries_csv(path: Path, runs: dict[str, LcdRun]) -> None:
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["detector", "keyframe", "frame", "match_frame", "score", "correct", "has_loop"])
        for name, run in runs.items():
            for r in run.records:
                writer.writerow(
                    [
                        name,
                        r.keyframe,
                        r.frame,
                        r.match_frame,
                        f"{r.score:.6f}",
                        int(r.correct),
                        int(r.has_loop),
                    ]
                )


def plot_pr(path: Path, runs: dict[str, LcdRun], title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4))
    for name, run in runs.items():
        scores = np.array([r.score for r in run.records])
        correct = np.array([r.correct for r in run.records])
        positives = sum(r.has_loop for r in run.records)
        _, precision, recall = precision_recall_curve(scores, correct, positives)
        ax.plot(recall, precision, drawstyle="steps-post", label=name)
    ax.set(xlabel="recall", ylabel="precision", xlim=(0, 1.02), ylim=(0, 1.02), title=title)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower left")
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
        "--detector",
        default="symbiolcd2",
        help="loop detector name (see `symbio detectors`), or several comma separated: one pass over "
        "the dataset, features and objects computed once, a comparison table",
    )
    parser.add_argument(
        "--object-detector", help="object detector (default: oracle on synthetic scenes, else ssd-mobilenet)"
    )
    parser.add_argument("--tolerance", type=int, default=0, help="frames a match may be off a GT reference")
    parser.add_argument("--keyframe-period", type=float, default=0.2, help="seconds between keyframes")
    parser.add_argument("--config", type=Path, help="YAML of the loop detector's config")
    parser.add_argument(
        "--wl-backend",
        choices=("ours", "grakel"),
        help="symbiolcd2 detectors: the WL kernel implementation (grakel: the slow reference)",
    )
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
    overrides = list(args.overrides)
    if args.wl_backend:
        overrides.append(f"wl_backend={args.wl_backend}")
    names = [name.strip() for name in args.detector.split(",") if name.strip()]
    if not names or len(set(names)) != len(names):
        raise ConfigError(f"--detector {args.detector!r}: give distinct detector names, comma separated")
    detectors = [LOOP_DETECTORS.load(name)(overrides, args.config) for name in names]
    object_name = args.object_detector or default_object_detector(dataset)
    objects = OBJECT_DETECTORS.load(object_name)(args.object_overrides)
    orb = load_config(OrbConfig, None, args.orb_overrides)
    runs = run_lcd(
        dataset, detectors, objects, orb, args.keyframe_period, args.tolerance, not args.no_progress
    )
    results = {
        name: {
            "detector": name,
            "object_detector": object_name,
            "tolerance": args.tolerance,
            **figures_of(run, detector.threshold),
            **detector_counters(detector),
        }
        for name, detector, run in zip(names, detectors, runs, strict=True)
    }
    print(f"eval lcd on {dataset.root} ({dataset.format_name}, {runs[0].keyframes} keyframes)")
    if len(names) == 1:
        print_figures(results[names[0]])
        write_json(args.json, results[names[0]])
    else:
        print(comparison_table(results))
        write_json(
            args.json, {f"{name}.{k}": v for name, figures in results.items() for k, v in figures.items()}
        )
    if args.csv:
        write_queries_csv(args.csv, dict(zip(names, runs, strict=True)))
    if args.plot:
        plot_pr(args.plot, dict(zip(names, runs, strict=True)), dataset.root.name)
    return 0


COMPARED = ("recall_at_100p", "auc_pr", "precision", "recall", "ms_detector_p50", "loop_detector_failures")


def comparison_table(results: dict[str, dict[str, Any]]) -> str:
    """A markdown table of the main figures, one row per detector."""
    lines = ["| detector | " + " | ".join(COMPARED) + " |", "|---" * (len(COMPARED) + 1) + "|"]
    for name, figures in results.items():
        cells = [
            f"{figures[key]:.3f}" if isinstance(figures[key], float) else str(figures[key])
            for key in COMPARED
        ]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def add_parser(subparsers: Any) -> None:
    evaluate = subparsers.add_parser("eval", help="evaluate loop detectors and SLAM runs")
    commands = evaluate.add_subparsers(dest="eval_command", metavar="SUBCOMMAND", required=True)
    add_lcd_parser(commands)
    # eval.table builds on this module (run_lcd, figures_of), so it is imported when the parser is built.
    from eval.table import add_table_parsers

    add_table_parsers(commands)
    detectors = subparsers.add_parser("detectors", help="list the installed loop and object detectors")
    detectors.set_defaults(handler=list_detectors)


def list_detectors(args: argparse.Namespace) -> int:
    for title, registry in (("loop detectors", LOOP_DETECTORS), ("object detectors", OBJECT_DETECTORS)):
        print(f"{title} (entry points: {registry.group}):")
        for name in registry.names():
            print(f"  {name:<22} {registry.origin(name)}")
    return 0
