"""``symbio eval table`` and ``symbio eval sweep``: the paper's experiments as commands, on Dask.

``symbio eval table --config eval/configs/paper.yaml --out DIR`` runs, per dataset of the config:

* Table II: precision and recall (at each detector's own threshold; recall at 100 % precision and
  PR-AUC too) of ``symbiolcd2``, ``vbow`` and the ML baselines of ``eval.paper.baselines`` (SVM-RBF,
  decision tree, 4x16 network, SymbioLCD's Random Forest on the tabular pair features, trained on
  the config's ``train`` split of synthetic seeds >= 100, never on a test scene);
* Table III: the ablation ``symbiolcd2-flat`` / ``symbiolcd2-two-tier`` / ``symbiolcd2``;
* Tables IV-V: ``repeats`` runs with seeds ``first_seed`` ... (the oracle's missed objects and the
  classifiers' randomness change with the seed; the paper used 50) and the Autorank analysis of
  precision and recall over the paired (dataset, seed) samples, with critical-difference diagrams;
* Table VI: the full pipeline (``symbio run``: frontend, detector, verification, GTSAM) per
  ``pipeline_detectors`` entry on every dataset with GT poses: the keyframe (and frame) of the
  first accepted loop that is true (within the dataset's tolerance of a GT loop pair), the first
  accepted loop of any kind, and the ATE (evo, Sim(3)-aligned) before and after loop closing.

Every (dataset, detector, seed) LCD run and every pipeline run is one job of ``eval.paper.sweep``: a Dask
task (a LocalCluster sized to the machine, or ``--scheduler ADDRESS``) whose result is stored in
``DIR/results/`` under the hash of its spec, so rerunning an interrupted command redoes only the
missing jobs and gives the same tables. A failing job is listed (``failures.csv``, the report) and
its samples are left out; the other jobs run on. Datasets in the config that are not present are
listed as skipped, so one config serves users with different data.

Writes ``DIR/report.html`` (the index), ``table2_lcd.md``, ``table2_recall_at_100p.md``,
``table3_ablation.md``, ``table4_autorank_precision.md``, ``table5_autorank_recall.md``,
``table6_earliest_loop.md``, ``jobs.csv`` (every job's figures), ``failures.csv``, ``pr_<dataset>.png``,
``cd_precision.png``, ``cd_recall.png`` and the pipeline runs (with ``trajectory_top.png``) under
``runs/``. Rendered synthetic scenes and training tables are cached under ``DIR/scenes``, ``DIR/train``.

``symbio eval sweep --config SWEEP.yaml --out DIR`` runs one registry detector over a grid of its
config values (``grid: {alpha: [0, 1, 2], iterations: [3, 10]}``) on the config's datasets and
seeds, with the same store, resume and failure handling, and writes ``sweep.csv`` and ``sweep.md``
(mean figures per grid point).

Relative dataset paths in a config are resolved against the current directory (run from the
repository root for the shipped configs' ``../shared/...``).
"""

from __future__ import annotations

import argparse
import csv
import html
import itertools
import json
import logging
import os
import shutil
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from eval.lcd_eval import LcdRun, QueryRecord, default_object_detector, figures_of, plot_pr, run_lcd
from eval.lcd_metrics import gt_references, is_true_match
from eval.paper.baselines import BASELINE_NAMES, TrainSplit, build_baseline, render_scene, scaled_synth_config
from eval.paper.stats import RankAnalysis, StatsMode, plot_critical_difference, rank_detectors
from eval.paper.sweep import (
    ClusterOptions,
    JobFailure,
    JobResult,
    JobSpec,
    ResultStore,
    SweepOutcome,
    dask_client,
    job_key,
    run_jobs,
)
from frontends.cli_common import add_json_option, write_json
from frontends.config import apply_mapping, config_to_dict, parse_override, read_yaml_mapping
from frontends.datasets import open_dataset
from frontends.errors import ConfigError, SymbioError
from frontends.orb import OrbConfig
from frontends.safe_yaml import short_repr
from frontends.synth import SynthConfig
from frontends.synth.world import TrajectoryKind
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS, LoopDetector
from lcd.symbiolcd import load_table, save_table

log = logging.getLogger(__name__)

#: Part of every job spec: bump when what a job computes changes, so stored results are not reused.
JOB_VERSION = 1
#: Figures of a pipeline run kept in its job result.
PIPELINE_FIGURES = (
    "ate_rmse_before",
    "ate_rmse_after",
    "keyframes",
    "frames",
    "frames_tracked",
    "segments",
    "loops_proposed",
    "loops_verified",
    "loops_accepted",
    "false_loops_accepted",
    "fps",
)


@dataclass(frozen=True)
class DatasetEntry:
    """One dataset of a table or sweep config: a folder any reader opens, or a synthetic scene."""

    name: str = ""
    #: Dataset folder (or video); relative paths are resolved against the current directory.
    path: str = ""
    #: Reader (``tum``, ``kitti``, ``euroc``, ``loops`` ...); empty: detected from the layout.
    format: str = ""
    #: Intrinsics YAML overriding the dataset's.
    calib: str = ""
    #: Render a synthetic scene of this trajectory (``loop``, ``figure8``, ``out-and-back``) instead.
    synthetic: str = ""
    #: Synthetic scenes: scene seed (evaluation range 0-99), frames and resolution.
    seed: int = 0
    frames: int = 600
    width: int = 640
    height: int = 480
    #: Frames a match may be off a GT reference.
    tolerance: int = 3
    #: Empty: the oracle on synthetic scenes, ssd-mobilenet elsewhere.
    object_detector: str = ""
    #: The oracle's share of missed objects (seeded by the repeat's seed).
    miss_rate: float = 0.3
    keyframe_period: float = 0.2
    #: Run the full pipeline for Table VI (needs GT poses; skipped on loop-pairs sets).
    pipeline: bool = True

    def __post_init__(self) -> None:
        if not self.name:
            raise ConfigError("dataset entry without a name")
        if bool(self.path) == bool(self.synthetic):
            raise ConfigError(f"dataset {self.name!r}: give exactly one of path and synthetic")


@dataclass(frozen=True)
class TableConfig:
    """``symbio eval table``: what runs; the datasets come from the YAML's ``datasets`` list."""

    #: Runs per (dataset, detector) with seeds first_seed, first_seed + 1, ... (the paper: 50).
    repeats: int = 3
    first_seed: int = 0
    #: Compared with the baselines in Table II and ranked in Tables IV-V.
    detectors: tuple[str, ...] = ("vbow", "symbiolcd2")
    baselines: tuple[str, ...] = BASELINE_NAMES
    #: Table III.
    ablation: tuple[str, ...] = ("symbiolcd2-flat", "symbiolcd2-two-tier", "symbiolcd2")
    #: Table VI: full pipeline runs (one per dataset with GT poses and detector, seed first_seed).
    pipeline_detectors: tuple[str, ...] = ("vbow", "symbiolcd", "symbiolcd2")
    frontend: str = "mono-vo"
    train: TrainSplit = field(default_factory=TrainSplit)
    #: Autorank's significance level and mode.
    alpha: float = 0.05
    stats_mode: StatsMode = "nonparametric"
    datasets: tuple[DatasetEntry, ...] = ()

    def __post_init__(self) -> None:
        if self.repeats < 1:
            raise ConfigError(f"repeats must be >= 1, got {self.repeats}")
        unknown = [b for b in self.baselines if b not in BASELINE_NAMES]
        if unknown:
            raise ConfigError(f"unknown baselines {unknown} (known: {', '.join(BASELINE_NAMES)})")

    @property
    def seeds(self) -> list[int]:
        return list(range(self.first_seed, self.first_seed + self.repeats))

    @property
    def compared(self) -> list[str]:
        """Table II's columns: the classic baseline, the ML baselines, then the detectors."""
        return list(dict.fromkeys([*self.detectors[:-1], *self.baselines, *self.detectors[-1:]]))


@dataclass(frozen=True)
class SweepConfig:
    """``symbio eval sweep``: one detector over a grid of its config values."""

    detector: str = "symbiolcd2"
    #: Config key -> values; every combination is one grid point.
    grid: dict[str, list[Any]] = field(default_factory=dict)
    repeats: int = 1
    first_seed: int = 0
    datasets: tuple[DatasetEntry, ...] = ()

    @property
    def points(self) -> list[tuple[str, ...]]:
        keys = list(self.grid)
        return [
            tuple(
                f"{k}={yaml.safe_dump(v, default_flow_style=True).strip().removesuffix('...').strip()}"
                for k, v in zip(keys, values, strict=True)
            )
            for values in itertools.product(*(self.grid[k] for k in keys))
        ]


def load_experiment_config(
    cls: type[TableConfig] | type[SweepConfig], path: Path, overrides: Sequence[str] = ()
) -> Any:
    """A table or sweep config from YAML: every key checked, errors naming the file and line."""
    mapping, lines = read_yaml_mapping(path)
    entries = mapping.pop("datasets", [])
    grid = mapping.pop("grid", None) if cls is SweepConfig else None
    config = apply_mapping(cls(), mapping, source=str(path), lines=lines)
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{path}:{lines.get('datasets', 1)}: 'datasets' must be a non-empty list")
    datasets = []
    for index, item in enumerate(entries):
        where = f"{path}:{lines.get(f'datasets.{index}', lines.get('datasets', 1))}"
        if not isinstance(item, dict):
            raise ConfigError(f"{where}: each dataset must be a mapping (name:, path: or synthetic: ...)")
        try:
            datasets.append(apply_mapping(DatasetEntry(name="_", path="_"), {"path": "", **item}, where))
        except ConfigError as exc:
            message = str(exc)
            raise ConfigError(message if message.startswith(where) else f"{where}: {message}") from None
    names = [d.name for d in datasets]
    if len(set(names)) != len(names):
        raise ConfigError(
            f"{path}:{lines.get('datasets', 1)}: dataset names must be distinct, got {short_repr(names)}"
        )
    changes: dict[str, Any] = {"datasets": tuple(datasets)}
    if grid is not None:
        if not isinstance(grid, dict) or not all(isinstance(v, list) and v for v in grid.values()):
            raise ConfigError(f"{path}:{lines.get('grid', 1)}: 'grid' must map config keys to lists")
        changes["grid"] = {str(k): list(v) for k, v in grid.items()}
    config = replace(config, **changes)
    for item in overrides:
        nested, source = parse_override(item)
        config = apply_mapping(config, nested, source=source)
    return config


# --- datasets ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ResolvedDataset:
    entry: DatasetEntry
    folder: Path
    object_detector: str
    #: The scene to render first (synthetic entries).
    synth: SynthConfig | None
    #: Whether the dataset has GT poses (pipeline runs make sense).
    has_poses: bool

    def spec(self, seed: int) -> dict[str, Any]:
        """The dataset part of a job spec; the oracle's misses are seeded by ``seed``."""
        entry = self.entry
        oracle = self.object_detector == "oracle"
        return {
            "name": entry.name,
            "folder": str(self.folder),
            "format": entry.format,
            "calib": str(Path(entry.calib).resolve()) if entry.calib else "",
            "tolerance": entry.tolerance,
            "keyframe_period": entry.keyframe_period,
            "object_detector": self.object_detector,
            "object_overrides": [f"miss_rate={entry.miss_rate}", f"seed={seed}"] if oracle else [],
        }


def resolve_datasets(
    entries: Sequence[DatasetEntry], work: Path
) -> tuple[list[ResolvedDataset], dict[str, str]]:
    """The datasets that can run, and why each other one is skipped (name -> reason)."""
    resolved, skipped = [], {}
    for entry in entries:
        if entry.synthetic:
            if entry.synthetic not in ("loop", "figure8", "out-and-back", "none"):
                raise ConfigError(f"dataset {entry.name!r}: unknown synthetic trajectory {entry.synthetic!r}")
            trajectory: TrajectoryKind = entry.synthetic  # type: ignore[assignment]
            synth = scaled_synth_config(trajectory, entry.seed, entry.frames, entry.width, entry.height)
            folder = work / "scenes" / f"{entry.name}_{job_key(config_to_dict(synth))}"
            resolved.append(
                ResolvedDataset(entry, folder.resolve(), entry.object_detector or "oracle", synth, True)
            )
            continue
        folder = Path(os.path.expandvars(entry.path)).expanduser().resolve()
        if not folder.exists():
            skipped[entry.name] = f"not found: {folder}"
            continue
        try:
            dataset = open_dataset(folder, entry.format or None, calib=entry.calib or None)
            pairs, _ = dataset.loop_pairs()
        except SymbioError as exc:
            skipped[entry.name] = f"cannot be read: {exc}"
            continue
        if pairs is None:
            skipped[entry.name] = "no ground-truth loops (no loop-pairs file and no GT poses)"
            continue
        objects = entry.object_detector or default_object_detector(dataset)
        resolved.append(ResolvedDataset(entry, folder, objects, None, dataset.has_groundtruth))
    return resolved, skipped


def open_spec_dataset(data: Mapping[str, Any]) -> Any:
    return open_dataset(Path(data["folder"]), data["format"] or None, calib=data["calib"] or None)


# --- jobs ----------------------------------------------------------------------------------------


def lcd_spec(
    dataset: ResolvedDataset,
    detector: str,
    seed: int,
    train: TrainSplit | None,
    work: Path,
    overrides: Sequence[str] = (),
) -> dict[str, Any]:
    """One LCD job. Seeds matter for seeded objects (the oracle) and for trained baselines only; other
    jobs are run once and their result stands for every seed."""
    seeded = train is not None or dataset.object_detector == "oracle"
    spec: dict[str, Any] = {
        "kind": "lcd",
        "version": JOB_VERSION,
        "dataset": dataset.spec(seed if seeded else 0),
        "detector": detector,
        "overrides": list(overrides),
        "seed": seed if seeded else 0,
    }
    if train is not None:
        spec["train"] = config_to_dict(train)
        spec["work"] = str(work.resolve())
    return spec


def pipeline_spec(
    dataset: ResolvedDataset, detector: str, seed: int, frontend: str, work: Path
) -> dict[str, Any]:
    return {
        "kind": "pipeline",
        "version": JOB_VERSION,
        "dataset": dataset.spec(seed),
        "detector": detector,
        "frontend": frontend,
        "seed": seed,
        "out": str((work / "runs" / f"{dataset.entry.name}_{detector}").resolve()),
    }


def execute_job(spec: JobSpec) -> JobResult:
    """Run one job (on a Dask worker)."""
    if spec["kind"] == "lcd":
        return lcd_job(spec)
    if spec["kind"] == "pipeline":
        return pipeline_job(spec)
    raise ConfigError(f"unknown job kind {spec['kind']!r}")


def training_table_path(train: Mapping[str, Any], seed: int, work: Path) -> Path:
    return work / "train" / f"{job_key({'train': train, 'seed': seed, 'version': JOB_VERSION})}.npz"


def cached_training_table(train: Mapping[str, Any], seed: int, work: Path) -> Path:
    """The split's training table for ``seed``, built once (atomically) under ``work/train``."""
    from eval.paper.baselines import training_table

    path = training_table_path(train, seed, work)
    if not path.is_file():
        split = apply_mapping(TrainSplit(), train, source="training split")
        table = training_table(split, work / "scenes", seed)
        temporary = path.with_suffix(f".{os.getpid()}.tmp")
        save_table(temporary, table, {"seed": seed, "scenes": ",".join(split.scenes)})
        os.replace(temporary, path)
    return path


def make_detector(spec: JobSpec) -> LoopDetector:
    name = spec["detector"]
    if "train" in spec:
        work = Path(spec["work"])
        table = load_table(cached_training_table(spec["train"], spec["seed"], work))
        return build_baseline(name, table, spec["seed"])
    return LOOP_DETECTORS.load(name)(spec["overrides"])


def lcd_job(spec: JobSpec) -> JobResult:
    data = spec["dataset"]
    dataset = open_spec_dataset(data)
    detector = make_detector(spec)
    objects = OBJECT_DETECTORS.load(data["object_detector"])(data["object_overrides"])
    run = run_lcd(
        dataset, [detector], objects, OrbConfig(), data["keyframe_period"], data["tolerance"], progress=False
    )[0]
    figures = figures_of(run, detector.threshold)
    accepted_true = [r for r in run.records if r.correct and r.score >= detector.threshold]
    return {
        "figures": figures,
        "first_true_keyframe": accepted_true[0].keyframe if accepted_true else None,
        "first_true_frame": accepted_true[0].frame if accepted_true else None,
        "records": [
            [r.keyframe, r.frame, r.match_frame, r.score, r.correct, r.has_loop] for r in run.records
        ],
    }


def pipeline_job(spec: JobSpec) -> JobResult:
    from eval.components import Components
    from eval.run import LOOPS_FILE, build_slam, run_odometry

    data = spec["dataset"]
    dataset = open_spec_dataset(data)
    components = Components(
        frontend=spec["frontend"],
        detector=spec["detector"],
        object_detector=data["object_detector"],
        overrides={"object_detector": list(data["object_overrides"])},
    )
    slam = build_slam(dataset, components)
    out = Path(spec["out"])
    figures = run_odometry(dataset, slam, out, progress=False, tolerance=data["tolerance"])
    pairs, _ = dataset.loop_pairs()
    references = gt_references(pairs) if pairs is not None else {}
    first_true: dict[str, Any] | None = None
    first_any: dict[str, Any] | None = None
    with (out / LOOPS_FILE).open(encoding="utf-8") as handle:
        for row in csv.DictReader(handle):
            if row["accepted"] != "1":
                continue
            loop = {"keyframe": int(row["query"]), "frame": int(row["query_frame"])}
            first_any = first_any or loop
            true = is_true_match(
                int(row["match_frame"]), references.get(int(row["query_frame"])), data["tolerance"]
            )
            if true and first_true is None:
                first_true = loop
    return {
        "figures": {k: figures.get(k) for k in PIPELINE_FIGURES},
        "first_true": first_true,
        "first_accepted": first_any,
        "trajectory_png": str(out / "trajectory_top.png"),
    }


def prepare(client: Any, scenes: Sequence[tuple[SynthConfig, Path]]) -> dict[Path, str]:
    """Render the scenes not rendered yet, one task each; returns folder -> error for failures."""
    missing = [(c, f) for c, f in scenes if not (f / "gt_loop_pairs.txt").is_file()]
    futures = {client.submit(render_scene, c, f, key=f"render-{f.name}", pure=False): f for c, f in missing}
    errors = {}
    for future, folder in futures.items():
        if future.status != "error":
            future.result()
        if future.status == "error":
            errors[folder] = f"rendering failed: {future.exception()!r}"
    return errors


# --- the table command -----------------------------------------------------------------------------


@dataclass
class TableRun:
    config: TableConfig
    datasets: list[ResolvedDataset]
    skipped: dict[str, str]
    outcome: SweepOutcome
    lcd: dict[tuple[str, str, int], JobResult]
    pipeline: dict[tuple[str, str], JobResult]


def lcd_detectors(config: TableConfig) -> list[str]:
    return list(dict.fromkeys([*config.compared, *config.ablation]))


def table_specs(
    config: TableConfig, datasets: Sequence[ResolvedDataset], work: Path
) -> tuple[dict[tuple[str, str, int], dict[str, Any]], dict[tuple[str, str], dict[str, Any]]]:
    lcd = {
        (d.entry.name, name, seed): lcd_spec(
            d, name, seed, config.train if name in config.baselines else None, work
        )
        for d in datasets
        for name in lcd_detectors(config)
        for seed in config.seeds
    }
    pipeline = {
        (d.entry.name, name): pipeline_spec(d, name, config.first_seed, config.frontend, work)
        for d in datasets
        if d.entry.pipeline and d.has_poses
        for name in config.pipeline_detectors
    }
    return lcd, pipeline


def run_table(config: TableConfig, out: Path, cluster: ClusterOptions) -> TableRun:
    out.mkdir(parents=True, exist_ok=True)
    datasets, skipped = resolve_datasets(config.datasets, out)
    lcd, pipeline = table_specs(config, datasets, out)
    store = ResultStore(out / "results")
    done = [0]

    def report(spec: JobSpec, result: JobResult) -> None:
        done[0] += 1
        figures = result["figures"]
        what = (
            f"P {figures['precision']:.3f} R {figures['recall']:.3f}"
            if spec["kind"] == "lcd"
            else f"ATE {figures['ate_rmse_before']} -> {figures['ate_rmse_after']}"
        )
        print(
            f"[{done[0]}] {spec['kind']} {spec['dataset']['name']} {spec['detector']} "
            f"seed {spec['seed']}: {what}",
            flush=True,
        )

    with dask_client(cluster) as client:
        scenes = [(d.synth, d.folder) for d in datasets if d.synth is not None]
        if any(name in config.baselines for _, name, _ in lcd):
            scenes += config.train.scene_folders(out / "scenes")
        for folder, error in prepare(client, scenes).items():
            for d in datasets:
                if d.folder == folder:
                    skipped[d.entry.name] = error
        datasets = [d for d in datasets if d.entry.name not in skipped]
        lcd = {k: v for k, v in lcd.items() if k[0] not in skipped}
        pipeline = {k: v for k, v in pipeline.items() if k[0] not in skipped}
        pending_seeds = sorted({s["seed"] for s in lcd.values() if "train" in s and not store.has(s)})
        train = config_to_dict(config.train)
        tables = [
            client.submit(cached_training_table, train, seed, out, key=f"train-{seed}", pure=False)
            for seed in pending_seeds
        ]
        for future in tables:
            if future.status != "error":
                future.exception()  # wait; a failure shows again in each baseline job of that seed
        specs = [*lcd.values(), *pipeline.values()]
        unique = {job_key(s): s for s in specs}.values()
        print(
            f"eval table: {len(unique)} jobs, {sum(store.has(s) for s in unique)} already in {store.root}",
            flush=True,
        )
        outcome = run_jobs(client, specs, execute_job, store, report)
    return TableRun(
        config,
        datasets,
        skipped,
        outcome,
        {k: r for k, s in lcd.items() if (r := outcome.result(s)) is not None},
        {k: r for k, s in pipeline.items() if (r := outcome.result(s)) is not None},
    )


def mean_figure(run: TableRun, dataset: str, detector: str, key: str) -> float | None:
    values = [
        r["figures"][key]
        for seed in run.config.seeds
        if (r := run.lcd.get((dataset, detector, seed))) is not None
    ]
    values = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.mean(values)) if values else None


def mean_of(values: Sequence[float | None]) -> float | None:
    present = [v for v in values if v is not None]
    return float(np.mean(present)) if present else None


def _cell(value: float | None, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def lcd_markdown(run: TableRun, detectors: Sequence[str], keys: tuple[str, str]) -> str:
    """Rows: datasets and their average; per detector two columns (``keys``, mean over the repeats);
    the best value of each column pair in bold."""
    names = [d.entry.name for d in run.datasets]
    short = {"precision": "P", "recall": "R", "recall_at_100p": "R@100%P", "auc_pr": "AUC"}
    header = "| dataset | " + " | ".join(f"{d} {short.get(k, k)}" for d in detectors for k in keys) + " |"
    lines = [header, "|---" * (1 + 2 * len(detectors)) + "|"]
    rows = {n: {(d, k): mean_figure(run, n, d, k) for d in detectors for k in keys} for n in names}
    average = {(d, k): mean_of([rows[n][(d, k)] for n in names]) for d in detectors for k in keys}
    for label, row in [*rows.items(), ("average", average)]:
        cells = []
        for k in keys:
            present = [v for d in detectors if (v := row[(d, k)]) is not None]
            best = max(present, default=None)
            for d in detectors:
                value = row[(d, k)]
                text = _cell(value)
                bold = value is not None and best is not None and bool(np.isclose(value, best))
                cells.append(f"**{text}**" if bold else text)
        # Cells were built key by key; the header lists them detector by detector.
        cells = [cells[i * len(detectors) + j] for j in range(len(detectors)) for i in range(len(keys))]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def paired_samples(run: TableRun, detectors: Sequence[str], key: str) -> dict[str, list[float]]:
    """One value per (dataset, seed) and detector; a sample missing for any detector is left out."""
    samples: dict[str, list[float]] = {d: [] for d in detectors}
    for dataset in run.datasets:
        for seed in run.config.seeds:
            results = [run.lcd.get((dataset.entry.name, d, seed)) for d in detectors]
            if all(r is not None for r in results):
                for d, r in zip(detectors, results, strict=True):
                    assert r is not None
                    samples[d].append(float(r["figures"][key]))
    return samples


def autorank_analyses(run: TableRun) -> dict[str, RankAnalysis | str]:
    analyses: dict[str, RankAnalysis | str] = {}
    for key in ("precision", "recall"):
        try:
            analyses[key] = rank_detectors(
                paired_samples(run, run.config.compared, key), key, run.config.alpha, run.config.stats_mode
            )
        except (ConfigError, ValueError) as exc:
            analyses[key] = f"autorank not run: {exc}"
    return analyses


def earliest_markdown(run: TableRun) -> str:
    detectors = run.config.pipeline_detectors
    lines = [
        "| dataset | "
        + " | ".join(f"{d} first true loop kf (frame) | {d} ATE before → after" for d in detectors)
        + " |",
        "|---" * (1 + 2 * len(detectors)) + "|",
    ]
    for dataset in run.datasets:
        if not any((dataset.entry.name, d) in run.pipeline for d in detectors):
            continue
        cells = []
        for d in detectors:
            result = run.pipeline.get((dataset.entry.name, d))
            if result is None:
                cells += ["failed", "failed"]
                continue
            first = result["first_true"]
            cells.append(f"{first['keyframe']} ({first['frame']})" if first else "none")
            figures = result["figures"]
            cells.append(f"{_cell(figures['ate_rmse_before'], 4)} → {_cell(figures['ate_rmse_after'], 4)}")
        lines.append(f"| {dataset.entry.name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def lcd_run_of(result: JobResult) -> LcdRun:
    """The stored records of an LCD job as ``eval.lcd_eval``'s run, for its PR plot."""
    run = LcdRun()
    for keyframe, frame, match, score, correct, has_loop in result["records"]:
        run.records.append(QueryRecord(keyframe, frame, match, score, correct, has_loop, 0.0, 0.0, 0.0))
    return run


def write_jobs_csv(path: Path, run: TableRun) -> None:
    keys = (
        "precision",
        "recall",
        "recall_at_100p",
        "auc_pr",
        "queries",
        "queries_with_loop",
        "true_positives",
        "false_positives",
        "ms_detector_p50",
    )
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["dataset", "detector", "seed", *keys, "first_true_keyframe"])
        for (dataset, detector, seed), result in sorted(run.lcd.items()):
            figures = result["figures"]
            writer.writerow(
                [dataset, detector, seed, *(figures.get(k) for k in keys), result["first_true_keyframe"]]
            )


def write_failures_csv(path: Path, failures: Sequence[JobFailure]) -> None:
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["kind", "dataset", "detector", "seed", "error"])
        for f in failures:
            writer.writerow(
                [f.spec["kind"], f.spec["dataset"]["name"], f.spec["detector"], f.spec["seed"], f.error]
            )


def markdown_to_html(text: str) -> str:
    """Pipe tables as HTML tables, other lines as paragraphs (enough for our own markdown)."""
    parts: list[str] = []
    rows: list[list[str]] = []

    def cells(row: list[str], tag: str) -> str:
        return "".join(f"<{tag}>{c}</{tag}>" for c in row)

    def flush() -> None:
        if rows:
            head, *body = rows
            parts.append(
                "<table><tr>"
                + cells(head, "th")
                + "</tr>"
                + "".join(f"<tr>{cells(r, 'td')}</tr>" for r in body)
                + "</table>"
            )
            rows.clear()

    for line in text.splitlines():
        if line.startswith("|"):
            if not set(line) <= set("|-: "):
                texts = [html.escape(c.strip()) for c in line.strip("|").split("|")]
                rows.append([f"<b>{c.strip('*')}</b>" if c.startswith("**") else c for c in texts])
        else:
            flush()
            if line.strip():
                parts.append(f"<p>{html.escape(line)}</p>")
    flush()
    return "\n".join(parts)


def write_table_outputs(run: TableRun, out: Path) -> dict[str, Any]:
    """Every table (markdown + CSV), plot and the report; returns the flat figures for ``--json``."""
    config = run.config
    sections: list[tuple[str, str, list[str]]] = []
    table2 = lcd_markdown(run, config.compared, ("precision", "recall"))
    table2b = lcd_markdown(run, config.compared, ("recall_at_100p", "auc_pr"))
    table3 = lcd_markdown(run, config.ablation, ("precision", "recall"))
    (out / "table2_lcd.md").write_text(table2 + "\n", encoding="utf-8")
    (out / "table2_recall_at_100p.md").write_text(table2b + "\n", encoding="utf-8")
    (out / "table3_ablation.md").write_text(table3 + "\n", encoding="utf-8")
    pr_images = []
    for dataset in run.datasets:
        runs = {
            d: lcd_run_of(r)
            for d in lcd_detectors(config)
            if (r := run.lcd.get((dataset.entry.name, d, config.first_seed))) is not None
        }
        if runs:
            image = out / f"pr_{dataset.entry.name}.png"
            plot_pr(image, runs, f"{dataset.entry.name} (seed {config.first_seed})")
            pr_images.append(image.name)
    sections.append(
        (
            f"Table II: precision / recall at each detector's threshold (mean of {config.repeats} repeats)",
            table2,
            pr_images,
        )
    )
    sections.append(("Table II (cont.): recall at 100 % precision / area under the PR curve", table2b, []))
    sections.append(("Table III: ablation flat / two-tier / three-tier", table3, []))
    figures: dict[str, Any] = {}
    for number, (key, analysis) in zip((4, 5), autorank_analyses(run).items(), strict=True):
        if isinstance(analysis, str):
            text, images = analysis, []
        else:
            text = analysis.markdown()
            image = out / f"cd_{key}.png"
            images = [image.name] if plot_critical_difference(analysis, image) else []
            figures[f"autorank_{key}_best"] = analysis.ranks[0].name
            figures[f"autorank_{key}_p_value"] = analysis.p_value
        (out / f"table{number}_autorank_{key}.md").write_text(text + "\n", encoding="utf-8")
        sections.append((f"Table {'IV' if number == 4 else 'V'}: Autorank analysis ({key})", text, images))
    table6 = earliest_markdown(run)
    (out / "table6_earliest_loop.md").write_text(table6 + "\n", encoding="utf-8")
    trajectories = []
    for (dataset_name, detector), result in sorted(run.pipeline.items()):
        source = Path(result["trajectory_png"])
        if source.is_file():
            target = out / f"trajectory_{dataset_name}_{detector}.png"
            shutil.copyfile(source, target)
            trajectories.append(target.name)
    sections.append(
        (
            "Table VI: earliest true loop accepted by the full pipeline, and ATE (m) before → after",
            table6,
            trajectories,
        )
    )
    write_jobs_csv(out / "jobs.csv", run)
    write_failures_csv(out / "failures.csv", run.outcome.failures)
    notes = [f"skipped dataset {name}: {reason}" for name, reason in run.skipped.items()]
    notes += [
        f"failed job {f.spec['kind']} {f.spec['dataset']['name']} {f.spec['detector']} "
        f"seed {f.spec['seed']}: {f.error}"
        for f in run.outcome.failures
    ]
    write_report(out / "report.html", config, sections, notes, run.outcome)
    for (dataset_name, detector, seed), result in run.lcd.items():
        if seed == config.first_seed:
            for key in ("precision", "recall", "recall_at_100p", "auc_pr"):
                figures[f"{dataset_name}.{detector}.{key}"] = result["figures"][key]
    figures.update(
        jobs_run=run.outcome.executed,
        jobs_reused=run.outcome.reused,
        jobs_failed=len(run.outcome.failures),
        datasets_skipped=len(run.skipped),
    )
    return figures


def write_report(
    path: Path,
    config: TableConfig,
    sections: Sequence[tuple[str, str, list[str]]],
    notes: Sequence[str],
    outcome: SweepOutcome,
) -> None:
    body = [
        f"<h1>symbio eval table</h1><p>{outcome.executed} jobs run, {outcome.reused} reused from the result "
        f"store, {len(outcome.failures)} failed; {outcome.seconds:.0f} s.</p>"
    ]
    body += [f"<p class=note>{html.escape(n)}</p>" for n in notes]
    for title, text, images in sections:
        body.append(f"<h2>{html.escape(title)}</h2>{markdown_to_html(text)}")
        body += [f'<img src="{html.escape(i)}" alt="{html.escape(i)}">' for i in images]
    settings = html.escape(json.dumps({k: v for k, v in asdict(config).items() if k != "datasets"}, indent=1))
    body.append(f"<h2>Configuration</h2><pre>{settings}</pre>")
    style = (
        "body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;margin:1em 0}"
        "td,th{border:1px solid #bbb;padding:2px 6px;text-align:right}img{max-width:520px;margin:4px}"
        ".note{color:#a40}"
    )
    path.write_text(
        "<!doctype html><html><head><meta charset=utf-8><title>symbio eval table</title>"
        f"<style>{style}</style></head><body>{''.join(body)}</body></html>\n",
        encoding="utf-8",
    )


def add_job_arguments(parser: argparse.ArgumentParser, config_help: str, repeats_help: str) -> None:
    """What ``table`` and ``sweep`` share: the config, the result store, repeats and the cluster."""
    parser.add_argument("--config", type=Path, required=True, help=config_help)
    parser.add_argument(
        "--out", type=Path, required=True, metavar="DIR", help="output folder and result store"
    )
    parser.add_argument("--repeats", type=int, help=repeats_help)
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="address of a running Dask scheduler (default: a LocalCluster of one worker per core)",
    )
    parser.add_argument("--workers", type=int, help="local workers (default: one per core)")
    parser.add_argument(
        "--dashboard",
        metavar="ADDRESS",
        help="serve the local cluster's Dask dashboard at HOST:PORT, e.g. 127.0.0.1:8787 (:8787 listens on "
        "every interface, unauthenticated); default: no dashboard, everything on 127.0.0.1",
    )
    add_json_option(parser)


def add_table_parsers(commands: Any) -> None:
    """``symbio eval table`` and ``symbio eval sweep`` (siblings of ``symbio eval lcd``)."""
    table = commands.add_parser(
        "table",
        help="the paper's experiments (Tables II-VI) on the datasets of a config, as Dask jobs",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_job_arguments(
        table,
        "experiment YAML (eval/configs/paper.yaml)",
        "runs per (dataset, detector), overriding the config",
    )
    table.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a top-level config value",
    )
    table.set_defaults(handler=run_table_command)
    sweep = commands.add_parser(
        "sweep",
        help="one loop detector over a grid of its config values on the datasets of a config, as Dask jobs",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_job_arguments(
        sweep, "sweep YAML (detector, grid, datasets)", "seeds per grid point, overriding the config"
    )
    sweep.set_defaults(handler=run_sweep_command)


def run_table_command(args: argparse.Namespace) -> int:
    overrides = [*args.overrides, *([f"repeats={args.repeats}"] if args.repeats is not None else [])]
    config: TableConfig = load_experiment_config(TableConfig, args.config, overrides)
    run = run_table(config, args.out, ClusterOptions(args.scheduler, args.workers, dashboard=args.dashboard))
    figures = write_table_outputs(run, args.out)
    for name, reason in run.skipped.items():
        print(f"note: dataset {name} skipped: {reason}")
    for failure in run.outcome.failures:
        print(
            f"failed: {failure.spec['kind']} {failure.spec['dataset']['name']} {failure.spec['detector']} "
            f"seed {failure.spec['seed']}: {failure.error}"
        )
    for name in (
        "table2_lcd.md",
        "table3_ablation.md",
        "table4_autorank_precision.md",
        "table5_autorank_recall.md",
        "table6_earliest_loop.md",
    ):
        print(f"\n{name}\n{(args.out / name).read_text(encoding='utf-8')}")
    print(f"wrote {args.out / 'report.html'}")
    write_json(args.json, figures)
    return 0


# --- the sweep command ---------------------------------------------------------------------------

SWEEP_KEYS = ("precision", "recall", "recall_at_100p", "auc_pr")


def run_sweep(config: SweepConfig, out: Path, cluster: ClusterOptions) -> tuple[SweepOutcome, list[str]]:
    points = config.points or [()]
    for point in points:  # a wrong key or value fails now, naming it, not in every job
        LOOP_DETECTORS.load(config.detector)(list(point))
    out.mkdir(parents=True, exist_ok=True)
    datasets, skipped = resolve_datasets(config.datasets, out)
    notes = [f"dataset {name} skipped: {reason}" for name, reason in skipped.items()]
    seeds = range(config.first_seed, config.first_seed + config.repeats)
    with dask_client(cluster) as client:
        for folder, error in prepare(
            client, [(d.synth, d.folder) for d in datasets if d.synth is not None]
        ).items():
            notes.append(f"{folder}: {error}")
            datasets = [d for d in datasets if d.folder != folder]
        specs = [
            lcd_spec(d, config.detector, s, None, out, p) for d in datasets for p in points for s in seeds
        ]
        outcome = run_jobs(client, specs, execute_job, ResultStore(out / "results"))
    rows: list[tuple[JobSpec, dict[str, Any]]] = []
    for spec in specs:
        result = outcome.result(spec)
        if result is not None:
            rows.append((spec, result["figures"]))
    with (out / "sweep.csv").open("w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow(["dataset", "seed", "parameters", *SWEEP_KEYS])
        for job, figures in rows:
            writer.writerow(
                [
                    job["dataset"]["name"],
                    job["seed"],
                    " ".join(job["overrides"]),
                    *(figures[k] for k in SWEEP_KEYS),
                ]
            )
    lines = [
        f"| {config.detector} | " + " | ".join(SWEEP_KEYS) + " | jobs |",
        "|---" * (len(SWEEP_KEYS) + 2) + "|",
    ]
    for point in points:
        values = [f for s, f in rows if tuple(s["overrides"]) == point]
        means = [_cell(float(np.mean([v[k] for v in values]))) if values else "-" for k in SWEEP_KEYS]
        lines.append(f"| {' '.join(point) or 'defaults'} | " + " | ".join(means) + f" | {len(values)} |")
    (out / "sweep.md").write_text("\n".join(lines) + "\n", encoding="utf-8")
    notes += [
        f"failed job {f.spec['dataset']['name']} {' '.join(f.spec['overrides'])} "
        f"seed {f.spec['seed']}: {f.error}"
        for f in outcome.failures
    ]
    return outcome, notes


def run_sweep_command(args: argparse.Namespace) -> int:
    overrides = [f"repeats={args.repeats}"] if args.repeats is not None else []
    config: SweepConfig = load_experiment_config(SweepConfig, args.config, overrides)
    outcome, notes = run_sweep(
        config, args.out, ClusterOptions(args.scheduler, args.workers, dashboard=args.dashboard)
    )
    for note in notes:
        print(f"note: {note}")
    print((args.out / "sweep.md").read_text(encoding="utf-8"))
    print(
        f"{outcome.executed} jobs run, {outcome.reused} reused, {len(outcome.failures)} failed; "
        f"wrote {args.out}"
    )
    write_json(
        args.json,
        {
            "jobs_run": outcome.executed,
            "jobs_reused": outcome.reused,
            "jobs_failed": len(outcome.failures),
            "seconds": outcome.seconds,
        },
    )
    return 0
