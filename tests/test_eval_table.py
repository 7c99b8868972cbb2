"""``symbio eval table`` / ``sweep`` end to end on a tiny synthetic scene, the configs, and the statistics."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from eval.cli import main
from eval.paper.stats import effect, rank_detectors
from eval.paper.sweep import ClusterOptions, ResultStore
from eval.paper.table import (
    SweepConfig,
    TableConfig,
    TableRun,
    load_experiment_config,
    run_sweep,
    run_table,
    write_table_outputs,
)
from frontends.errors import ConfigError

REPO_ROOT = Path(__file__).resolve().parent.parent
SMOKE = REPO_ROOT / "eval" / "configs" / "smoke.yaml"
PAPER = REPO_ROOT / "eval" / "configs" / "paper.yaml"
THREADS = ClusterOptions(workers=2, processes=False)
TABLES = ("table2_lcd.md", "table2_recall_at_100p.md", "table3_ablation.md", "table4_autorank_precision.md",
          "table5_autorank_recall.md", "table6_earliest_loop.md")  # fmt: skip


def smoke_config() -> TableConfig:
    """The smoke config, cut to one baseline; ``no-such-detector`` makes five jobs fail."""
    config: TableConfig = load_experiment_config(TableConfig, SMOKE)
    return dataclasses.replace(
        config, baselines=("decision-tree",), ablation=("symbiolcd2", "no-such-detector")
    )


@pytest.fixture(scope="module")
def table_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[TableRun, Path]:
    out = tmp_path_factory.mktemp("table")
    run = run_table(smoke_config(), out, THREADS)
    write_table_outputs(run, out)
    return run, out


def test_configs_load_and_name_their_datasets() -> None:
    paper: TableConfig = load_experiment_config(TableConfig, PAPER)
    names = [d.name for d in paper.datasets]
    assert {"rtabmap_samples", "fr2-desk", "fr3-long-office"} <= set(names)
    assert sum(bool(d.synthetic) for d in paper.datasets) >= 3
    assert paper.compared == [
        "vbow",
        "svm-rbf",
        "decision-tree",
        "neural-network",
        "symbiolcd-rf",
        "symbiolcd2",
    ]
    assert load_experiment_config(TableConfig, PAPER, ["repeats=50"]).seeds == list(range(50))


def test_config_errors_name_file_and_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("repeats: 2\ndatasets:\n  - name: a\n    synthetic: loop\n  - name: b\n    pth: x\n")
    with pytest.raises(ConfigError, match=rf"{bad}:5: .*unknown key 'pth'"):
        load_experiment_config(TableConfig, bad)
    bad.write_text("repeats: two\ndatasets: [{name: a, synthetic: loop}]\n")
    with pytest.raises(ConfigError, match=rf"{bad}:1: 'repeats'"):
        load_experiment_config(TableConfig, bad)
    bad.write_text("repeats: 2\n")
    with pytest.raises(ConfigError, match="'datasets' must be a non-empty list"):
        load_experiment_config(TableConfig, bad)
    bad.write_text("datasets: [{name: a, synthetic: loop, path: /x}]\n")
    with pytest.raises(ConfigError, match="exactly one of path and synthetic"):
        load_experiment_config(TableConfig, bad)


def test_autorank_on_known_inputs() -> None:
    rng = np.random.default_rng(0)
    base = rng.uniform(0.5, 0.6, 12)
    # Paired samples with a strict order on every sample: mean ranks 1, 2, 3 exactly.
    samples = {"worst": list(base), "best": list(base + 0.3), "middle": list(base + 0.1)}
    analysis = rank_detectors(samples, "recall")
    assert [r.name for r in analysis.ranks] == ["best", "middle", "worst"]
    assert [r.mean_rank for r in analysis.ranks] == [1.0, 2.0, 3.0]
    assert analysis.ranks[0].centre == pytest.approx(np.median(base + 0.3))
    assert analysis.ranks[2].spread == pytest.approx(np.median(np.abs(base - np.median(base))), rel=1e-3)
    assert analysis.omnibus == "friedman" and analysis.p_value < 0.001
    # Nemenyi critical difference for 3 populations, 12 samples: q_0.05 = 2.343 * sqrt(k(k+1)/(6N)).
    assert analysis.critical_difference == pytest.approx(2.343 * np.sqrt(3 * 4 / (6 * 12)), rel=1e-3)
    assert analysis.ranks[0].ci_lower <= analysis.ranks[0].centre <= analysis.ranks[0].ci_upper
    assert analysis.ranks[0].magnitude == "negligible" and analysis.ranks[2].magnitude == "large"
    table = analysis.markdown()
    assert table.splitlines()[0] == "| recall | MR | MED | MAD | CI | γ | Mag. |"
    assert "12 paired samples; friedman" in table
    with pytest.raises(ConfigError, match="at least 5"):
        rank_detectors({"a": [1, 2, 3], "b": [1, 2, 4]}, "recall")
    assert (effect(float("nan")), effect(-np.inf), effect(0.25)) == ("-", "-inf", "0.25")


@pytest.mark.slow
def test_table_structure_and_outputs(table_run: tuple[TableRun, Path]) -> None:
    _, out = table_run
    for name in (*TABLES, "report.html", "jobs.csv", "failures.csv", "pr_loop-3.png", "cd_recall.png"):
        assert (out / name).is_file(), name
    table2 = (out / "table2_lcd.md").read_text().splitlines()
    assert table2[0] == (
        "| dataset | vbow P | vbow R | decision-tree P | decision-tree R | symbiolcd2 P | symbiolcd2 R |"
    )
    assert [line.split("|")[1].strip() for line in table2[2:]] == ["loop-3", "average"]
    cells = [c.strip().strip("*") for c in table2[2].split("|")[2:-1]]
    assert all(0.0 <= float(c) <= 1.0 for c in cells)
    # Five repeats per (detector, seed) and every job of the three compared detectors stored.
    with (out / "jobs.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert sorted({r["detector"] for r in rows}) == ["decision-tree", "symbiolcd2", "vbow"]
    assert sorted(int(r["seed"]) for r in rows if r["detector"] == "decision-tree") == [0, 1, 2, 3, 4]
    recalls = {float(r["recall"]) for r in rows if r["detector"] == "decision-tree"}
    assert len(recalls) >= 1 and all(0 <= v <= 1 for v in recalls)
    autorank = (out / "table5_autorank_recall.md").read_text()
    assert "5 paired samples" in autorank
    assert {line.split("|")[1].strip() for line in autorank.splitlines()[2:5]} == {
        "vbow",
        "decision-tree",
        "symbiolcd2",
    }
    table6 = (out / "table6_earliest_loop.md").read_text().splitlines()
    assert table6[2].startswith("| loop-3 | ")
    report = (out / "report.html").read_text()
    assert "skipped dataset not-here: not found" in report
    assert "Table VI" in report and "<table>" in report


@pytest.mark.slow
def test_failing_jobs_are_isolated_and_listed(table_run: tuple[TableRun, Path]) -> None:
    run, out = table_run
    failed = run.outcome.failures
    assert len(failed) == 5 and {f.spec["detector"] for f in failed} == {"no-such-detector"}
    assert all("no-such-detector" in f.error for f in failed)
    with (out / "failures.csv").open() as handle:
        assert len(list(csv.DictReader(handle))) == 5
    # Its ablation columns are empty, the other detectors' are filled.
    ablation = (out / "table3_ablation.md").read_text().splitlines()[2].split("|")
    assert [c.strip() for c in ablation[4:6]] == ["-", "-"]
    assert ablation[2].strip() != "-"


@pytest.mark.slow
def test_resume_redoes_only_missing_jobs_and_gives_identical_tables(
    table_run: tuple[TableRun, Path], tmp_path: Path
) -> None:
    run, out = table_run
    before = {name: (out / name).read_text() for name in TABLES}
    store = ResultStore(out / "results")
    lcd_files = sorted(p for p in store.root.iterdir() if '"kind": "lcd"' in p.read_text())
    # An interrupted sweep: the last two LCD results never got written.
    for path in lcd_files[:2]:
        path.unlink()
    resumed = run_table(smoke_config(), out, THREADS)
    write_table_outputs(resumed, out)
    assert resumed.outcome.executed == 2
    assert resumed.outcome.reused == run.outcome.executed + run.outcome.reused - 2
    assert len(resumed.outcome.failures) == 5
    assert {name: (out / name).read_text() for name in TABLES} == before


@pytest.mark.slow
def test_sweep_over_a_grid(table_run: tuple[TableRun, Path], tmp_path: Path) -> None:
    _, out = table_run
    sweep = tmp_path / "sweep.yaml"
    sweep.write_text("detector: symbiolcd2\ngrid: {alpha: [0, 2]}\ndatasets: [{name: a, synthetic: loop}]\n")
    base: SweepConfig = load_experiment_config(SweepConfig, sweep)
    # The smoke config's scene: already rendered under ``out`` by the table run.
    config = dataclasses.replace(base, datasets=smoke_config().datasets[:1])
    outcome, notes = run_sweep(config, out, THREADS)
    assert not outcome.failures and not notes
    assert outcome.executed == 2
    lines = (out / "sweep.md").read_text().splitlines()
    assert lines[0].startswith("| symbiolcd2 | precision | recall")
    assert [line.split("|")[1].strip() for line in lines[2:]] == ["alpha=0", "alpha=2"]
    # alpha=2 is symbiolcd2's default: its recall equals the table's symbiolcd2 seed-0 job.
    with (out / "sweep.csv").open() as handle:
        rows = {r["parameters"]: r for r in csv.DictReader(handle)}
    with (out / "jobs.csv").open() as handle:
        table = [r for r in csv.DictReader(handle) if r["detector"] == "symbiolcd2" and r["seed"] == "0"]
    assert float(rows["alpha=2"]["recall_at_100p"]) == pytest.approx(float(table[0]["recall_at_100p"]))


def test_bad_grid_key_fails_before_any_job(tmp_path: Path) -> None:
    config = tmp_path / "sweep.yaml"
    config.write_text(
        "detector: symbiolcd2\ngrid: {no_such_key: [1, 2]}\ndatasets: [{name: a, synthetic: loop}]\n"
    )
    assert main(["eval", "sweep", "--config", str(config), "--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o").exists()


@pytest.mark.shared
def test_table_on_the_real_loop_set_matches_eval_lcd(shared: Path, tmp_path: Path) -> None:
    """The table's figures on the RTAB-Map samples are those of ``symbio eval lcd`` on the same set."""
    from eval.lcd_eval import figures_of, run_lcd
    from frontends.datasets import open_dataset
    from frontends.orb import OrbConfig
    from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS

    rtabmap = shared / "data" / "loops" / "rtabmap_samples"
    config = tmp_path / "real.yaml"
    config.write_text(
        "repeats: 5\ndetectors: [vbow, symbiolcd2]\nbaselines: [decision-tree]\nablation: [symbiolcd2]\n"
        "pipeline_detectors: [symbiolcd2]\n"
        "train: {scenes: ['loop:110'], frames: 240, width: 320, height: 240}\n"
        f"datasets:\n  - {{name: rtabmap, path: {rtabmap}, tolerance: 0}}\n"
    )
    out = tmp_path / "T"
    run = run_table(load_experiment_config(TableConfig, config), out, THREADS)
    write_table_outputs(run, out)
    assert not run.outcome.failures and not run.skipped
    # Deterministic detectors on CNN objects run once; the trained baseline once per seed.
    assert run.outcome.executed == 2 + 5
    assert not run.pipeline  # a loop-pairs set has no poses: no pipeline run
    dataset = open_dataset(rtabmap)
    objects = OBJECT_DETECTORS.load("ssd-mobilenet")()
    detectors = [LOOP_DETECTORS.load(name)() for name in ("vbow", "symbiolcd2")]
    direct = run_lcd(dataset, detectors, objects, OrbConfig(), 0.2, 0, progress=False)
    for detector, lcd in zip(detectors, direct, strict=True):
        expected = figures_of(lcd, detector.threshold)
        for seed in range(5):
            figures = run.lcd[("rtabmap", detector.name, seed)]["figures"]
            for key in ("precision", "recall", "recall_at_100p", "auc_pr"):
                assert figures[key] == pytest.approx(expected[key]), (detector.name, key)
    assert "5 paired samples" in (out / "table5_autorank_recall.md").read_text()
