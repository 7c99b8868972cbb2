"""``eval/bench_pipeline``: ``--set`` reaches every run (a bad value is a CLI error naming it)."""

from __future__ import annotations

from pathlib import Path

import pytest

from eval.bench.pipeline import main


def test_a_bad_setting_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--trajectories", "loop", "--seeds", "0", "--frames", "40", "--work", str(tmp_path)]
    with pytest.raises(SystemExit):
        main([*argv, "--set", "frontend.keyframes.search_radius=0"])
    assert "search_radius" in capsys.readouterr().err
