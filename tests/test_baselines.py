"""The paper's ML baselines: trained on a synthetic split disjoint from the test scene, then detecting."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from eval.lcd_eval import figures_of, run_lcd
from eval.paper.baselines import (
    BASELINE_NAMES,
    TrainSplit,
    build_baseline,
    scaled_synth_config,
    training_table,
)
from frontends.datasets import open_dataset
from frontends.errors import ConfigError
from frontends.orb import OrbConfig
from frontends.synth import write_scene
from lcd.base import OBJECT_DETECTORS
from lcd.symbiolcd import FEATURE_NAMES, TrainingTable

SPLIT = TrainSplit(scenes=("loop:110",), frames=240, width=320, height=240)


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("baselines")


@pytest.fixture(scope="module")
def table(work: Path) -> TrainingTable:
    return training_table(SPLIT, work / "scenes", seed=0)


@pytest.fixture(scope="module")
def test_scene(work: Path) -> Path:
    folder = work / "test_loop_3"
    write_scene(scaled_synth_config("loop", 3, 300, 320, 240), folder, progress=False)
    return folder


def test_training_table_has_both_classes_from_the_split(table: TrainingTable, work: Path) -> None:
    assert table.features.shape[1] == len(FEATURE_NAMES)
    assert len(table.labels) == len(table.features) > 100
    assert 0 < table.labels.sum() < len(table.labels)
    assert (work / "scenes" / "train_loop_110_240_320" / "scene.json").is_file()


@pytest.mark.parametrize("name", BASELINE_NAMES)
def test_baseline_fits_its_training_rows(name: str, table: TrainingTable) -> None:
    detector = build_baseline(name, table, seed=0)
    assert detector.name == name and detector.threshold == 0.5
    classifier = getattr(detector, "classifier", None) or detector.forest  # type: ignore[attr-defined]
    probability = classifier.predict_proba(table.features)[:, 1]
    assert probability.shape == table.labels.shape
    assert ((probability >= 0.5) == table.labels.astype(bool)).mean() > 0.8
    # Loops score higher than non-loops on average: the classifier learnt something.
    assert probability[table.labels == 1].mean() > probability[table.labels == 0].mean() + 0.2


def test_baselines_detect_loops_on_an_unseen_scene(table: TrainingTable, test_scene: Path) -> None:
    detectors = [build_baseline(name, table, seed=0) for name in BASELINE_NAMES]
    objects = OBJECT_DETECTORS.load("oracle")(["miss_rate=0.3", "seed=0"])
    runs = run_lcd(open_dataset(test_scene), detectors, objects, OrbConfig(), 0.2, 3, progress=False)
    for detector, run in zip(detectors, runs, strict=True):
        figures = figures_of(run, detector.threshold)
        assert figures["queries_with_loop"] > 5
        assert figures["auc_pr"] > 0.5, detector.name
        assert figures["true_positives"] > 0, detector.name


def test_seeds_change_the_randomised_classifiers(table: TrainingTable) -> None:
    a = build_baseline("neural-network", table, seed=0)
    b = build_baseline("neural-network", table, seed=1)
    pa = a.classifier.predict_proba(table.features)  # type: ignore[attr-defined]
    pb = b.classifier.predict_proba(table.features)  # type: ignore[attr-defined]
    assert not np.allclose(pa, pb)
    same = build_baseline("neural-network", table, seed=0)
    assert np.array_equal(pa, same.classifier.predict_proba(table.features))  # type: ignore[attr-defined]


def test_evaluation_seeds_cannot_be_trained_on() -> None:
    with pytest.raises(ConfigError, match="reserved for evaluation"):
        TrainSplit(scenes=("loop:110", "figure8:7"))
    with pytest.raises(ConfigError, match="TRAJECTORY:SEED"):
        TrainSplit(scenes=("spiral:120",))


def test_unknown_baseline_is_a_config_error(table: TrainingTable) -> None:
    with pytest.raises(ConfigError, match="unknown baseline"):
        build_baseline("xgboost", table, seed=0)
