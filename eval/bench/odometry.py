"""Robustness benchmark of the pipeline's odometry: map collapses and ATE over scene x frontend seeds.

The frontend is chaotic on the synthetic scenes: a rule that helps one scene often makes another
collapse, and which runs collapse changes with the frontend's RANSAC ``seed``. One run per scene
cannot tell two rules apart; this runs the pipeline's odometry (``bench_pipeline.run_scene``'s
"masked" mode: the full run's object detector masking movable objects, no loop closing) on every
(trajectory, scene seed) for several frontend seeds, in parallel processes, and reports per run the
ATE over every posed frame (evo, Sim(3)-aligned) and the segments; then the runs that collapse (ATE
above ``--collapse``, default 0.3 m: the collapsed maps of the 600-frame scenes end at 0.5-1.4 m, the
others below 0.25 m) and the geometric-mean ATE of the others. ``--against OLD.json`` (an earlier
``--json``) compares: collapses in each, and the geometric mean over the runs neither collapses.

Usage: ``python -m eval.bench.odometry [--trajectories loop,figure8,out-and-back] [--seeds 0-6]
[--frontend-seeds 0,1] [--frames 600] [--jobs 2] [--work DIR] [--set SECTION.key=value ...]
[--json OUT] [--against OLD.json]``. ``--set`` takes ``symbio run``'s keys (a key without a section
goes to the frontend), e.g. ``--set keyframes.search_neighbours=8 --set keyframes.tracked_ratio=0.7``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import tempfile
from collections.abc import Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from eval.bench.pipeline import run_scene
from eval.bench.scenes import parse_seeds, scene_folder
from frontends.cli_common import add_json_option, add_set_option, write_json
from frontends.errors import ConfigError

DEFAULT_COLLAPSE_M = 0.3


@dataclass(frozen=True)
class Job:
    trajectory: str
    seed: int
    frontend_seed: int

    @property
    def name(self) -> str:
        return f"{self.trajectory}_{self.seed}/seed{self.frontend_seed}"


@dataclass(frozen=True)
class Summary:
    runs: int
    collapses: list[str]
    #: Geometric-mean ATE (m) over the runs that did not collapse (None if all did).
    geometric_mean_ate: float | None


def summarise(ate: Mapping[str, float | None], collapse_m: float) -> Summary:
    """Runs above ``collapse_m`` (or without an ATE: nothing posed) collapse; the rest are averaged."""
    collapsed = [name for name, value in ate.items() if value is None or value > collapse_m]
    kept = [value for name, value in ate.items() if name not in collapsed and value is not None]
    return Summary(len(ate), collapsed, _geometric_mean(kept))


def compare(
    old: Mapping[str, float | None], new: Mapping[str, float | None], collapse_m: float
) -> dict[str, Any]:
    """Collapses of each over their common runs, and both geometric means over the runs neither
    collapses (a rule that collapses more runs but averages better elsewhere shows as both)."""
    common = [name for name in new if name in old]
    before = summarise({n: old[n] for n in common}, collapse_m)
    after = summarise({n: new[n] for n in common}, collapse_m)
    steady = [n for n in common if n not in before.collapses and n not in after.collapses]
    return {
        "runs": len(common),
        "collapses_old": len(before.collapses),
        "collapses_new": len(after.collapses),
        "steady_runs": len(steady),
        "steady_geometric_mean_old": _geometric_mean([old[n] for n in steady]),  # type: ignore[misc]
        "steady_geometric_mean_new": _geometric_mean([new[n] for n in steady]),  # type: ignore[misc]
        "steady_better": sum(new[n] < old[n] for n in steady),  # type: ignore[operator]
    }


def _geometric_mean(values: Sequence[float]) -> float | None:
    return math.exp(sum(math.log(v) for v in values) / len(values)) if values else None


def _render(args: tuple[str, int, int, Path]) -> Path:
    trajectory, seed, frames, work = args
    return scene_folder(work, trajectory, seed, frames)


def _run(args: tuple[Job, Path, Path, tuple[str, ...]]) -> tuple[str, dict[str, Any]]:
    job, folder, out, overrides = args
    logging.basicConfig(level=logging.ERROR)
    figures = run_scene(folder, out, "masked", (*overrides, f"frontend.seed={job.frontend_seed}"))
    return job.name, {
        "ate": figures.get("ate_rmse_after_all"),
        "segments": figures.get("segments"),
        "frames_tracked": figures.get("frames_tracked"),
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trajectories", default="loop,figure8,out-and-back")
    parser.add_argument("--seeds", default="0-6", help="scene seeds: 0,1,2 or 0-6 (default 0-6)")
    parser.add_argument("--frontend-seeds", default="0,1", help="the frontend's RANSAC seeds (default 0,1)")
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--jobs", type=int, default=2, help="parallel runs (default 2)")
    parser.add_argument("--work", type=Path, help="scene cache and run outputs (default: a temporary folder)")
    add_set_option(parser, "override a setting as in `symbio run --set` (repeatable)")
    parser.add_argument("--collapse", type=float, default=DEFAULT_COLLAPSE_M, help="collapse ATE (m)")
    parser.add_argument("--against", type=Path, help="an earlier --json of this benchmark to compare with")
    add_json_option(parser)
    args = parser.parse_args(argv)
    try:
        seeds, frontend_seeds = parse_seeds(args.seeds), parse_seeds(args.frontend_seeds)
        old = _load_runs(args.against) if args.against else None
    except ConfigError as error:
        parser.error(str(error))
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_odometry_"))
    trajectories = args.trajectories.split(",")
    jobs = [Job(t, s, f) for t in trajectories for s in seeds for f in frontend_seeds]
    rows: dict[str, dict[str, Any]] = {}
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        scenes = [(t, s, args.frames, work) for t in trajectories for s in seeds]
        folders = dict(zip([(t, s) for t, s, _, _ in scenes], pool.map(_render, scenes), strict=True))
        tasks = [
            (job, folders[job.trajectory, job.seed], work / "runs" / job.name.replace("/", "_"),
             tuple(args.overrides))
            for job in jobs
        ]  # fmt: skip
        try:
            for name, row in pool.map(_run, tasks):
                rows[name] = row
                print(name, row, flush=True)
        except ConfigError as error:  # a bad --set, raised in the first run
            parser.error(str(error))
    print_table(rows, args.collapse)
    ate = {name: row["ate"] for name, row in rows.items()}
    summary = summarise(ate, args.collapse)
    print(
        f"\n{summary.runs} runs, {len(summary.collapses)} collapse (ATE > {args.collapse} m)"
        f"{': ' + ', '.join(summary.collapses) if summary.collapses else ''}; geometric-mean ATE of the "
        f"others {_f(summary.geometric_mean_ate)} m"
    )
    if old is not None:
        c = compare(old, ate, args.collapse)
        print(
            f"against {args.against}: {c['runs']} common runs, collapses {c['collapses_old']} -> "
            f"{c['collapses_new']}; over the {c['steady_runs']} runs neither collapses, geometric-mean "
            f"ATE {_f(c['steady_geometric_mean_old'])} -> {_f(c['steady_geometric_mean_new'])} m, "
            f"better in {c['steady_better']}"
        )
    if args.json:
        write_json(
            args.json,
            {"overrides": " ".join(args.overrides), "collapse_m": args.collapse, "runs": len(rows),
             "collapses": len(summary.collapses), "geometric_mean_ate": summary.geometric_mean_ate,
             **{f"{name}:{key}": value for name, row in rows.items() for key, value in row.items()}},
        )  # fmt: skip
    return 0


def _load_runs(path: Path) -> dict[str, float | None]:
    """The per-run ATE of an earlier ``--json``."""
    try:
        figures = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise ConfigError(f"{path}: not a bench_odometry --json file ({error})") from None
    runs = {key.removesuffix(":ate"): value for key, value in figures.items() if key.endswith(":ate")}
    if not runs:
        raise ConfigError(f"{path}: no per-run ATE in it (not a bench_odometry --json file)")
    return runs


def print_table(rows: Mapping[str, Mapping[str, Any]], collapse_m: float) -> None:
    print("\n| run | ATE (m) | segments | frames posed | collapsed |")
    print("|---|---|---|---|---|")
    for name, row in rows.items():
        collapsed = "yes" if row["ate"] is None or row["ate"] > collapse_m else ""
        print(f"| {name} | {_f(row['ate'])} | {row['segments']} | {row['frames_tracked']} | {collapsed} |")


def _f(value: float | None) -> str:
    return "-" if value is None else f"{value:.4f}"


if __name__ == "__main__":
    sys.exit(main())
