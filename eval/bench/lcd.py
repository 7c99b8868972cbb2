"""Loop-detector accuracy across datasets: the comparison and ablation tables of
docs/loop-closure-detection.md ("Results").

Every dataset is read once per table: each keyframe's ORB features and objects are computed once and
fed to every detector (``eval.lcd_eval.run_lcd``), so the detectors see identical inputs.

Datasets:
- synthetic scenes rendered here (``symbio synth``, 900 frames = 30 s, 640x480): loops of seeds
  3, 7, 11, 12 and figure-8s of seeds 4, 13, with the ``oracle`` object detector missing 30 % of
  the objects, tolerance ``--synthetic-tolerance`` frames (default 3, half a keyframe step);
- ``../shared/data/loops/rtabmap_samples`` (real images, hand-labelled GT, ``ssd-mobilenet``
  objects, tolerance 0) when the shared folder is present (``--shared``, env ``SYMBIO_SHARED``).

``--sweep KEY=V1,V2,...`` adds one ``symbiolcd2`` per value (e.g. ``iterations=1,3,10,50`` for the
effect of h). Figures: recall at 100 % precision and the area under the PR curve per detector and
dataset, and the detector's own time per keyframe (features and objects excluded).

Usage: ``python -m eval.bench.lcd [--detectors a,b] [--sweep KEY=V,...] [--scenes DIR] [--json OUT]``.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eval.bench.scenes import scene_folder
from eval.lcd_eval import figures_of, run_lcd
from frontends.cli_common import add_json_option, write_json
from frontends.datasets import open_dataset
from frontends.orb import OrbConfig
from frontends.synth.world import TrajectoryKind
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS, LoopDetector

DEFAULT_DETECTORS = "vbow,symbiolcd,symbiolcd2-flat,symbiolcd2-two-tier,symbiolcd2"
SYNTHETIC_SCENES: tuple[tuple[TrajectoryKind, int], ...] = (
    ("loop", 3),
    ("loop", 7),
    ("loop", 11),
    ("loop", 12),
    ("figure8", 4),
    ("figure8", 13),
)
SYNTHETIC_FRAMES = 900


@dataclass(frozen=True)
class BenchDataset:
    name: str
    path: Path
    object_detector: str
    object_overrides: tuple[str, ...]
    tolerance: int


def synthetic_datasets(scenes: Path, tolerance: int, miss_rate: float) -> list[BenchDataset]:
    """Render the synthetic scenes into ``scenes`` once (reused while their config is unchanged)."""
    out = []
    for trajectory, seed in SYNTHETIC_SCENES:
        folder = scene_folder(scenes, trajectory, seed, SYNTHETIC_FRAMES)
        out.append(
            BenchDataset(f"{trajectory} {seed}", folder, "oracle", (f"miss_rate={miss_rate}",), tolerance)
        )
    return out


def detectors_to_compare(names: Sequence[str], sweep: str | None) -> dict[str, LoopDetector]:
    detectors = {name: LOOP_DETECTORS.load(name)() for name in names}
    if sweep:
        key, _, values = sweep.partition("=")
        for value in values.split(","):
            detectors[f"symbiolcd2 {key}={value}"] = LOOP_DETECTORS.load("symbiolcd2")([f"{key}={value}"])
    return detectors


def bench(args: argparse.Namespace) -> dict[str, dict[str, dict[str, float]]]:
    datasets = synthetic_datasets(args.scenes, args.synthetic_tolerance, args.miss_rate)
    rtabmap = args.shared / "data" / "loops" / "rtabmap_samples"
    if rtabmap.is_dir():
        datasets.insert(0, BenchDataset("rtabmap_samples", rtabmap, "ssd-mobilenet", (), 0))
    else:
        print(f"note: {rtabmap} not found; real-image row skipped", file=sys.stderr)
    names = [n.strip() for n in args.detectors.split(",") if n.strip()]
    table: dict[str, dict[str, dict[str, float]]] = {}
    for dataset in datasets:
        detectors = detectors_to_compare(names, args.sweep)
        objects = OBJECT_DETECTORS.load(dataset.object_detector)(list(dataset.object_overrides))
        runs = run_lcd(
            open_dataset(dataset.path),
            list(detectors.values()),
            objects,
            OrbConfig(),
            keyframe_period=0.2,
            tolerance=dataset.tolerance,
            progress=False,
        )
        for label, detector, run in zip(detectors, detectors.values(), runs, strict=True):
            figures = figures_of(run, detector.threshold)
            table.setdefault(label, {})[dataset.name] = {
                "recall_at_100p": figures["recall_at_100p"],
                "auc_pr": figures["auc_pr"],
                "ms_detector_p50": figures["ms_detector_p50"],
            }
        print(f"done: {dataset.name}", file=sys.stderr)
    return table


def markdown(table: dict[str, dict[str, dict[str, float]]]) -> str:
    datasets = list(next(iter(table.values())))
    lines = [
        "| detector | " + " | ".join(datasets) + " | mean | ms/kf |",
        "|---" * (len(datasets) + 3) + "|",
    ]
    for label, rows in table.items():
        recalls = [rows[d]["recall_at_100p"] for d in datasets]
        cells = [f"{rows[d]['recall_at_100p']:.3f} ({rows[d]['auc_pr']:.3f})" for d in datasets]
        ms = np.median([rows[d]["ms_detector_p50"] for d in datasets])
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {np.mean(recalls):.3f} | {ms:.1f} |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--detectors", default=DEFAULT_DETECTORS, help="comma-separated detector names")
    parser.add_argument("--sweep", metavar="KEY=V1,V2", help="add one symbiolcd2 per value of a config key")
    parser.add_argument("--scenes", type=Path, default=Path("bench_scenes"), help="cache of rendered scenes")
    parser.add_argument(
        "--shared", type=Path, default=Path(os.environ.get("SYMBIO_SHARED", "../shared")), help="shared data"
    )
    parser.add_argument("--synthetic-tolerance", type=int, default=3)
    parser.add_argument("--miss-rate", type=float, default=0.3, help="oracle miss rate on synthetic scenes")
    add_json_option(parser)
    args = parser.parse_args(argv)
    table = bench(args)
    print("recall at 100 % precision (area under the PR curve)")
    print(markdown(table))
    write_json(
        args.json,
        {
            f"{label}|{dataset}|{key}": value
            for label, rows in table.items()
            for dataset, figures in rows.items()
            for key, value in figures.items()
        },
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
