"""``eval/bench_relocalisation``: the blackout sequences, the summary, and a short CLI run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from eval.bench.relocalisation import Blackout, Outcome, main, summarise
from frontends.types import Frame


def frames(count: int) -> list[Frame]:
    pose = np.eye(4)
    return [Frame(i, i / 30, np.full((4, 4), 100 + i, np.uint8), None, pose) for i in range(count)]


@pytest.mark.parametrize(("resume", "first_source"), [("on", 15), ("back", 7)])
def test_blackout_sequences_resume_on_or_back_and_follow_on(resume: str, first_source: int) -> None:
    source = frames(40)
    sequence = Blackout(10, 5, resume, 3).sequence(source, after=8)  # type: ignore[arg-type]
    assert [f.index for f in sequence] == list(range(23))
    assert all(not f.image.any() for f in sequence[10:15])
    assert all(f.image[0, 0] == 100 + i for i, f in enumerate(sequence[:10]))
    # The resumed frames keep their own images and ground truth under the new numbers.
    assert [int(f.image[0, 0]) - 100 for f in sequence[15:]] == list(range(first_source, first_source + 8))
    assert sequence[15].timestamp == pytest.approx(15 / 30)


def test_summary_judges_relocalisations_on_right_maps_only() -> None:
    outcomes = [
        Outcome("a", "relocalised", 0.02, 0.5),
        Outcome("b", "relocalised", 0.40, 1.0),
        Outcome("c", "relocalised", 0.90, 7.0),  # the map was wrong before: not judged
        Outcome("d", "new segment", None, 0.5),
        Outcome("e", "no map before", None, None),
    ]
    summary = summarise(outcomes, map_error_percent=2.0, wrong_m=0.1)
    assert (summary["relocalised"], summary["new_segment"], summary["no_map_before"]) == (3, 1, 1)
    assert (summary["relocalised_on_right_maps"], summary["wrong_relocalisations"]) == (2, 1)
    assert summary["median_error_m"] == pytest.approx(0.21)


@pytest.mark.slow
def test_cli_reports_each_case_and_names_a_bad_setting(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    common = ["--trajectories", "loop", "--seeds", "0", "--frontend-seeds", "0", "--jobs", "1"]
    out = tmp_path / "r.json"
    assert main([*common, "--blackouts", "30", "--black", "5", "--after", "15", "--json", str(out)]) == 0
    figures = json.loads(out.read_text())
    assert figures["cases"] == 2
    # Back 3 frames into a well-mapped view, the camera relocalises close to the truth.
    assert figures["loop_0/seed0/30-back:result"] == "relocalised"
    assert figures["loop_0/seed0/30-back:error_m"] < 0.05
    assert "| loop_0/seed0/30-back |" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main([*common, "--set", "relocalisation.max_sigma_ratio=0"])
    assert "max_sigma_ratio" in capsys.readouterr().err
