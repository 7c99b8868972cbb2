"""The objects' ablation (issue 43): do the object tiers earn their place where the place is aliased?

Variants: ``vbow`` (bag of words), ``symbiolcd`` (v1), and SymbioLCD2 as ``flat`` (features only),
``two_tier`` (objects and the features inside their boxes) and ``three_tier`` (the paper's graph).
Scenes: the perceptually aliased synthetic set (``ALIASED_OVERRIDES``: rooms in a row with identical
walls, floor and ceiling that differ only in which objects stand where, revisited from the other
direction and lane; ``symbio synth --set layout=bays``), rendered once into ``--scenes``; and, one
row each, the real loop sets of the shared folder (``REAL_SETS``, ``ssd-mobilenet`` objects, one
deterministic sample; ``--no-real`` skips them).

Each repeat degrades the scene's ground-truth objects with the ``oracle`` detector (``--miss-rate``,
seed ``--seed`` + repeat: the paper's 50 repeats over the detector's randomness) and feeds every
variant the same keyframes (``eval.lcd_eval.run_lcd``: features and objects computed once); the
variants that never read objects (``OBJECT_BLIND``) run once per scene. One sample = one (scene,
repeat). Per variant: recall at 100 % precision and area under the PR curve, their mean and 95 %
confidence interval (Student t over the samples: the detector's randomness on these scenes, not the
choice of scenes), the objects per keyframe beside them, and autorank's Friedman / Nemenyi analysis
of the paired samples (``--plot``: its critical-difference diagram; needs >= 5 samples). Results:
docs/2026-12-06-objects-ablation.md.

Usage: ``python -m eval.bench_objects_ablation [--repeats 50] [--seed 0] [--scene-seeds 0,1,2]
[--frames 900] [--miss-rate 0.3] [--scenes DIR] [--jobs 2] [--no-real] [--plot CD.png] [--json OUT]``.
The flat JSON has ``recall_at_100p_<variant>``, ``ci95_low_<variant>``, ``ci95_high_<variant>``,
``auc_pr_<variant>``, ``objects_per_keyframe_mean``, ``samples`` and per scene
``<scene>|recall_at_100p_<variant>``.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from eval.bench.scenes import parse_seeds
from eval.lcd_eval import figures_of, run_lcd
from eval.paper.stats import RankAnalysis, plot_critical_difference, rank_detectors
from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.datasets import open_dataset
from frontends.errors import ConfigError
from frontends.orb import OrbConfig
from frontends.synth import SynthConfig, cached_scene
from frontends.types import DetectedObject, Frame
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS, ObjectDetector

#: Variant key -> registered loop detector.
VARIANTS = {
    "vbow": "vbow",
    "symbiolcd": "symbiolcd",
    "flat": "symbiolcd2-flat",
    "two_tier": "symbiolcd2-two-tier",
    "three_tier": "symbiolcd2",
}
#: Variants whose scores never use the objects: the same on every draw of the detector's misses.
OBJECT_BLIND = ("vbow", "flat")
#: The aliased layout (``frontends.synth``) every scene of the set uses; the seed varies.
ALIASED_OVERRIDES: dict[str, Any] = {"layout": "bays", "trajectory": "hall"}
#: The real loop sets of the shared folder scored beside the aliased scenes, and their detector.
REAL_SETS = ("rtabmap_samples", "gardens_point_day", "corridor")
REAL_OBJECT_DETECTOR = "ssd-mobilenet"
#: Keyframe spacing (s) and GT tolerance (frames: half a keyframe step), as ``eval.bench.lcd``.
KEYFRAME_PERIOD = 0.2
TOLERANCE = 3


@dataclass(frozen=True)
class Sample:
    scene: str
    repeat: int
    #: Variant key -> figures of ``figures_of``.
    figures: dict[str, dict[str, Any]]
    objects_per_keyframe: float


def aliased_config(seed: int, frames: int) -> SynthConfig:
    """The 640x480 aliased scene of ``seed`` with ``frames`` frames (30 fps)."""
    return replace(SynthConfig(seed=seed, frames=frames), **ALIASED_OVERRIDES)


def aliased_scene(scenes: Path, seed: int, frames: int) -> Path:
    """The aliased scene as a dataset folder under ``scenes``, rendered unless it is there already."""
    return cached_scene(aliased_config(seed, frames), scenes / f"aliased_{seed}_{frames}")


class _Counting:
    """An object detector that counts what it reports."""

    def __init__(self, inner: ObjectDetector) -> None:
        self.inner, self.name, self.counts = inner, inner.name, list[int]()

    def detect(self, image: np.ndarray, frame: Frame | None = None) -> list[DetectedObject]:
        found = self.inner.detect(image, frame)
        self.counts.append(len(found))
        return found


def _score(
    folder: Path, variants: Sequence[str], objects: ObjectDetector, tolerance: int
) -> tuple[dict[str, dict[str, Any]], float]:
    """The ``variants``' figures on one dataset (one ``run_lcd`` pass) and the objects per keyframe."""
    detectors = [LOOP_DETECTORS.load(VARIANTS[key])() for key in variants]
    counting = _Counting(objects)
    runs = run_lcd(
        open_dataset(folder), detectors, counting, OrbConfig(), KEYFRAME_PERIOD, tolerance, progress=False
    )
    figures = {
        key: figures_of(run, detector.threshold)
        for key, detector, run in zip(variants, detectors, runs, strict=True)
    }
    return figures, float(np.mean(counting.counts))


def run_repeat(folder: Path, repeat_seed: int, miss_rate: float, variants: Sequence[str]) -> Sample:
    """The ``variants`` on one scene with one draw of the detector's misses."""
    oracle = OBJECT_DETECTORS.load("oracle")([f"miss_rate={miss_rate}", f"seed={repeat_seed}"])
    figures, objects_per_keyframe = _score(folder, variants, oracle, TOLERANCE)
    return Sample(folder.name, repeat_seed, figures, objects_per_keyframe)


def run_scene(folder: Path, seeds: Sequence[int], miss_rate: float, jobs: int) -> list[Sample]:
    """One sample per seed. The variants that never look at objects (``OBJECT_BLIND``) give the same
    figures on every draw, so they run once and their figures are copied into every sample."""
    blind = run_repeat(folder, seeds[0], miss_rate, OBJECT_BLIND)
    seeing = [key for key in VARIANTS if key not in OBJECT_BLIND]
    tasks = [(folder, seed, miss_rate, seeing) for seed in seeds]
    if jobs > 1 and len(tasks) > 1:
        with ProcessPoolExecutor(jobs) as pool:
            drawn = list(pool.map(run_repeat, *zip(*tasks, strict=True)))
    else:
        drawn = [run_repeat(*task) for task in tasks]
    return [Sample(s.scene, s.repeat, {**blind.figures, **s.figures}, s.objects_per_keyframe) for s in drawn]


def real_sets(shared: Path) -> list[Path]:
    """The shared real loop sets there are (``REAL_SETS``), in that order."""
    loops = shared / "data" / "loops"
    return [loops / name for name in REAL_SETS if (loops / name).is_dir()]


def run_real(folder: Path) -> dict[str, Any]:
    """Every variant on one real loop set with the default CNN detector (deterministic: one sample):
    ``<set>|recall_at_100p_<variant>``, ``<set>|auc_pr_<variant>`` and ``<set>|objects_per_keyframe_mean``."""
    found, objects_per_keyframe = _score(
        folder, list(VARIANTS), OBJECT_DETECTORS.load(REAL_OBJECT_DETECTOR)(), 0
    )
    figures: dict[str, Any] = {}
    for key, variant in found.items():
        figures[f"{folder.name}|recall_at_100p_{key}"] = variant["recall_at_100p"]
        figures[f"{folder.name}|auc_pr_{key}"] = variant["auc_pr"]
    figures[f"{folder.name}|objects_per_keyframe_mean"] = objects_per_keyframe
    return figures


def interval(values: Sequence[float], level: float = 0.95) -> tuple[float, float, float]:
    """Mean of shares in [0, 1] and its Student-t confidence interval, clipped to [0, 1] (both ends at
    the mean when all values agree)."""
    data = np.asarray(values, dtype=np.float64)
    mean = float(data.mean())
    if len(data) < 2 or float(data.std()) == 0.0:
        return mean, mean, mean
    low, high = stats.t.interval(level, len(data) - 1, loc=mean, scale=stats.sem(data))
    return mean, max(float(low), 0.0), min(float(high), 1.0)


def summarise(samples: Sequence[Sample]) -> dict[str, Any]:
    figures: dict[str, Any] = {"samples": len(samples)}
    for key in VARIANTS:
        recalls = [s.figures[key]["recall_at_100p"] for s in samples]
        mean, low, high = interval(recalls)
        figures[f"recall_at_100p_{key}"] = mean
        figures[f"ci95_low_{key}"] = low
        figures[f"ci95_high_{key}"] = high
        figures[f"auc_pr_{key}"] = float(np.mean([s.figures[key]["auc_pr"] for s in samples]))
    figures["objects_per_keyframe_mean"] = float(np.mean([s.objects_per_keyframe for s in samples]))
    for scene in sorted({s.scene for s in samples}):
        mine = [s for s in samples if s.scene == scene]
        for key in VARIANTS:
            figures[f"{scene}|recall_at_100p_{key}"] = float(
                np.mean([s.figures[key]["recall_at_100p"] for s in mine])
            )
        figures[f"{scene}|objects_per_keyframe_mean"] = float(np.mean([s.objects_per_keyframe for s in mine]))
    return figures


def ranks(samples: Sequence[Sample]) -> RankAnalysis | None:
    """Autorank over the paired recall samples; None below its 5 samples."""
    if len(samples) < 5:
        return None
    paired = {key: [s.figures[key]["recall_at_100p"] for s in samples] for key in VARIANTS}
    return rank_detectors(paired, "recall_at_100p")


def markdown(figures: dict[str, Any], analysis: RankAnalysis | None) -> str:
    rows = [
        "| variant | recall at 100 % precision | 95 % CI | AUC PR | mean rank |",
        "|---|---|---|---|---|",
    ]
    mean_rank = {r.name: r.mean_rank for r in analysis.ranks} if analysis is not None else {}
    for key in VARIANTS:
        rank = f"{mean_rank[key]:.2f}" if key in mean_rank else "-"
        rows.append(
            f"| {key} | {figures[f'recall_at_100p_{key}']:.3f} | "
            f"[{figures[f'ci95_low_{key}']:.3f}, {figures[f'ci95_high_{key}']:.3f}] | "
            f"{figures[f'auc_pr_{key}']:.3f} | {rank} |"
        )
    rows.append(
        f"\n{figures['samples']} samples (scene x repeat), "
        f"{figures['objects_per_keyframe_mean']:.2f} objects per keyframe after the misses"
    )
    if analysis is not None:
        rows.append(
            f"autorank: {analysis.omnibus} p = {analysis.p_value:.3g}, critical difference "
            + (f"{analysis.critical_difference:.2f}" if analysis.critical_difference is not None else "n/a")
        )
    return "\n".join(rows)


def real_markdown(real: dict[str, Any]) -> str:
    names = sorted({key.split("|")[0] for key in real}, key=lambda n: REAL_SETS.index(n))
    rows = [
        f"\nreal loop sets ({REAL_OBJECT_DETECTOR}), recall at 100 % precision:",
        "| set | objects per keyframe | " + " | ".join(VARIANTS) + " |",
        "|---" * (len(VARIANTS) + 2) + "|",
    ]
    for name in names:
        cells = " | ".join(f"{real[f'{name}|recall_at_100p_{key}']:.3f}" for key in VARIANTS)
        rows.append(f"| {name} | {real[f'{name}|objects_per_keyframe_mean']:.2f} | {cells} |")
    return "\n".join(rows)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=50, help="detector draws per scene (paper: 50)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first draw (draw r: seed + r)")
    parser.add_argument("--scene-seeds", default="0,1,2", help="aliased scenes: 0,1,2 or 0-4")
    parser.add_argument("--frames", type=int, default=900, help="frames per scene (30 fps)")
    parser.add_argument("--miss-rate", type=float, default=0.3, help="oracle miss rate (default 0.3)")
    parser.add_argument("--scenes", type=Path, default=Path("bench_scenes"), help="cache of rendered scenes")
    parser.add_argument("--jobs", type=int, default=2, help="parallel processes (default 2)")
    parser.add_argument(
        "--shared",
        type=Path,
        default=Path(os.environ.get("SYMBIO_SHARED", "../shared")),
        help="shared data: its real loop sets get one row each (default $SYMBIO_SHARED or ../shared)",
    )
    parser.add_argument("--no-real", action="store_true", help="skip the real loop sets")
    parser.add_argument("--plot", type=Path, help="write the critical-difference diagram (PNG)")
    add_json_option(parser)
    args = parser.parse_args(argv)
    try:
        if args.repeats < 1:
            raise ConfigError(f"--repeats must be >= 1, got {args.repeats}")
        folders = [aliased_scene(args.scenes, seed, args.frames) for seed in parse_seeds(args.scene_seeds)]
        samples = []
        seeds = [args.seed + repeat for repeat in range(args.repeats)]
        for folder in folders:
            samples += run_scene(folder, seeds, args.miss_rate, args.jobs)
            print(f"done: {folder.name}", file=sys.stderr)
        analysis = ranks(samples)
        real: dict[str, Any] = {}
        for folder in [] if args.no_real else real_sets(args.shared):
            real.update(run_real(folder))
            print(f"done: {folder.name}", file=sys.stderr)
    except ConfigError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    figures = {**summarise(samples), **real}
    print(markdown(figures, analysis))
    if real:
        print(real_markdown(real))
    if args.plot is not None and analysis is not None and not plot_critical_difference(analysis, args.plot):
        print("note: autorank drew no critical-difference diagram (no significant difference)")
    print_figures({k: v for k, v in figures.items() if "|" not in k})
    write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
