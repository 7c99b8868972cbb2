"""``eval.bench.objects_ablation``: paired samples per (scene, draw), the object-blind variants run once,
confidence intervals, and the flat JSON the issue names."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from eval.bench import objects_ablation as ablation


def test_interval_is_a_clipped_student_t_interval() -> None:
    assert ablation.interval([0.5, 0.5, 0.5]) == (0.5, 0.5, 0.5)
    mean, low, high = ablation.interval([0.2, 0.4, 0.6, 0.8])
    assert mean == pytest.approx(0.5)
    # t(0.975, 3) = 3.182; sem = 0.2582 / 2
    assert high - mean == pytest.approx(3.182 * np.std([0.2, 0.4, 0.6, 0.8], ddof=1) / 2, rel=1e-3)
    assert low == pytest.approx(2 * mean - high)
    assert ablation.interval([0.0, 1.0]) == (0.5, 0.0, 1.0)


@pytest.mark.slow
def test_draws_change_only_the_object_variants(small_loop_scene: Path) -> None:
    samples = ablation.run_scene(small_loop_scene, [0, 1, 2], miss_rate=0.6, jobs=1)
    assert [s.repeat for s in samples] == [0, 1, 2]
    for key in ablation.OBJECT_BLIND:
        assert len({json.dumps(s.figures[key], sort_keys=True) for s in samples}) == 1
    # Different misses: different objects per keyframe, and the objects' variants see them.
    assert len({s.objects_per_keyframe for s in samples}) == 3
    seeing = {
        json.dumps([s.figures[k]["recall_at_100p"] for k in ("two_tier", "three_tier")], sort_keys=True)
        for s in samples
    }
    assert len(seeing) > 1
    figures = ablation.summarise(samples)
    for key in ablation.VARIANTS:
        assert figures[f"ci95_low_{key}"] <= figures[f"recall_at_100p_{key}"] <= figures[f"ci95_high_{key}"]
    assert figures["samples"] == 3
    assert figures["objects_per_keyframe_mean"] == pytest.approx(
        np.mean([s.objects_per_keyframe for s in samples])
    )


def test_bad_repeats_is_a_clear_error(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert ablation.main(["--repeats", "0", "--scenes", str(tmp_path)]) == 2
    assert "--repeats must be >= 1" in capsys.readouterr().err


@pytest.mark.shared
@pytest.mark.slow
def test_real_rows_use_the_cnn_detector(shared: Path) -> None:
    """RTAB-Map's 84 real images: ssd-mobilenet finds 0.38 objects per keyframe (most images none);
    the variants score as in ``eval.bench.lcd`` (vbow 0.977, symbiolcd2 0.955 at 100 % precision)."""
    folders = ablation.real_sets(shared)
    assert [f.name for f in folders] == list(ablation.REAL_SETS)
    figures = ablation.run_real(folders[0])
    assert 0.2 < figures["rtabmap_samples|objects_per_keyframe_mean"] < 1.0
    assert figures["rtabmap_samples|recall_at_100p_vbow"] >= 0.9
    assert figures["rtabmap_samples|recall_at_100p_three_tier"] >= 0.9
    assert set(figures) == {
        f"rtabmap_samples|{kind}_{key}" for kind in ("recall_at_100p", "auc_pr") for key in ablation.VARIANTS
    } | {"rtabmap_samples|objects_per_keyframe_mean"}
