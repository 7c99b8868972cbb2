"""``eval/bench_odometry``: seed parsing, the collapse summary and comparison, and a short CLI run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from eval.bench.odometry import compare, main, parse_seeds, summarise
from frontends.errors import ConfigError


def test_seeds_take_lists_and_ranges() -> None:
    assert parse_seeds("0-2,5") == [0, 1, 2, 5]
    assert parse_seeds("3") == [3]
    with pytest.raises(ConfigError, match="0-6"):
        parse_seeds("a-b")


def test_collapses_are_counted_and_left_out_of_the_mean() -> None:
    summary = summarise({"a": 0.01, "b": 0.04, "c": 0.9, "d": None}, 0.3)
    assert summary.runs == 4 and summary.collapses == ["c", "d"]
    assert summary.geometric_mean_ate == pytest.approx(0.02)


def test_comparison_separates_collapses_from_accuracy() -> None:
    old = {"a": 0.02, "b": 0.02, "c": 0.8, "gone": 0.01}
    new = {"a": 0.01, "b": 0.04, "c": 0.02, "x": 0.5}
    c = compare(old, new, 0.3)
    assert (c["runs"], c["collapses_old"], c["collapses_new"], c["steady_runs"]) == (3, 1, 0, 2)
    assert c["steady_geometric_mean_old"] == pytest.approx(0.02)
    assert c["steady_geometric_mean_new"] == pytest.approx(0.02)
    assert c["steady_better"] == 1


@pytest.mark.slow
def test_cli_runs_compares_and_names_a_bad_setting(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    common = ["--trajectories", "loop", "--seeds", "0", "--frontend-seeds", "0", "--frames", "40"]
    common += ["--jobs", "1"]
    first = tmp_path / "first.json"
    assert main([*common, "--work", str(tmp_path), "--json", str(first)]) == 0
    figures = json.loads(first.read_text())
    assert figures["runs"] == 1 and "loop_0/seed0:ate" in figures and "loop_0/seed0:segments" in figures
    capsys.readouterr()
    assert main([*common, "--work", str(tmp_path), "--against", str(first)]) == 0
    assert "1 common runs" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main([*common, "--work", str(tmp_path), "--set", "keyframes.search_neighbours=-1"])
    assert "search_neighbours" in capsys.readouterr().err
