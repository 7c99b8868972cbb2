"""The KITTI 00 mono-drift acceptance run of ``symbio posegraph`` (needs ../shared)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from eval.cli import main


@pytest.mark.shared
def test_kitti00_mono_drift_30_percent_false_loops(shared: Path, tmp_path: Path) -> None:
    out = tmp_path / "p.json"
    plot = tmp_path / "p.png"
    gt = shared / "data" / "trajectories" / "KITTI_00_gt.txt"
    argv = ["posegraph", "--trajectory", str(gt), "--format", "kitti", "--simulate", "mono-drift"]
    assert main([*argv, "--outliers", "0.3", "--seed", "1", "--json", str(out), "--plot", str(plot)]) == 0
    figures = json.loads(out.read_text())
    assert figures["loops_false"] > 0.2 * (figures["loops_true"] + figures["loops_false"])
    assert figures["false_accepted"] == 0
    assert figures["ate_rmse_optimized"] * 5 <= figures["ate_rmse_odometry"]
    assert plot.stat().st_size > 0
