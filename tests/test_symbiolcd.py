"""The SymbioLCD (v1) detector: pair features, training table, Random Forest scoring, training CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from eval.cli import main as symbio_main
from frontends.datasets import open_dataset
from frontends.errors import ConfigError, InputFileError
from frontends.gt_loops import read_loop_pairs
from frontends.orb import extract_orb
from frontends.synth import SynthConfig, write_scene
from frontends.types import DetectedObject, Keyframe
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS, LoopDetector
from lcd.symbiolcd import (
    FEATURE_NAMES,
    NO_LAYOUT_HAUSDORFF,
    SymbioLCD,
    SymbioLCDConfig,
    TrainingTable,
    create,
    load_table,
    pair_features,
    save_table,
)
from lcd.symbiolcd_train import check_not_evaluation_scene

CHAIR = DetectedObject("chair", 0.9, (10, 10, 120, 150))
TV = DetectedObject("tv", 0.8, (180, 20, 300, 100))
CUP = DetectedObject("cup", 0.9, (200, 150, 240, 200))


def place_keyframe(
    index: int, place: int, objects: tuple[DetectedObject, ...] = (CHAIR, TV), count: int = 300
) -> Keyframe:
    """Keyframe ``index`` seeing ``place``: the same place always gives the same random ORB features."""
    rng = np.random.default_rng(place)
    keypoints = rng.uniform(0, 320, size=(count, 2)).astype(np.float32)
    descriptors = rng.integers(0, 256, size=(count, 32), dtype=np.uint8)
    return Keyframe(index, index, float(index), np.eye(4), keypoints, descriptors, objects)


def rule_table(seed: int = 0, rows: int = 400) -> TrainingTable:
    """A table whose loops are the pairs with a high vBoW score and agreeing labels."""
    rng = np.random.default_rng(seed)
    features = np.column_stack(
        [
            rng.uniform(0, 1, rows),
            rng.uniform(0, 1, rows),
            rng.choice([0.0, 0.5, 1.0], rows),
            rng.uniform(0, NO_LAYOUT_HAUSDORFF, rows),
            rng.integers(0, 5, rows),
            rng.integers(0, 5, rows),
        ]
    )
    labels = ((features[:, 0] > 0.4) & (features[:, 2] >= 0.5)).astype(np.int64)
    return TrainingTable(features, labels)


def test_pair_features() -> None:
    row = dict(zip(FEATURE_NAMES, pair_features(0.2, 0.4, (CHAIR, TV), (CHAIR, TV)), strict=True))
    assert row["vbow"] == pytest.approx(0.2) and row["vbow_relative"] == pytest.approx(0.5)
    assert row["label_ratio"] == 1.0 and row["hausdorff"] == pytest.approx(0.0)
    assert row["query_objects"] == row["candidate_objects"] == 2
    # Fewer than two objects: no normalised plane, labels alone give the ratio.
    lone = dict(zip(FEATURE_NAMES, pair_features(0.1, 0.1, (CHAIR,), (CHAIR, CUP)), strict=True))
    assert lone["hausdorff"] == NO_LAYOUT_HAUSDORFF and lone["label_ratio"] == pytest.approx(0.5)
    empty = dict(zip(FEATURE_NAMES, pair_features(0.1, 0.1, (), (CHAIR,)), strict=True))
    assert empty["label_ratio"] == 0.0 and empty["query_objects"] == 0


def test_contract_window_and_revisit() -> None:
    detector = create(["temporal_window=3"])
    assert LOOP_DETECTORS.load("symbiolcd") is create and isinstance(detector, LoopDetector)
    assert detector.name == "symbiolcd" and isinstance(detector.threshold, float)
    assert detector.temporal_window == 3
    for index in range(12):
        candidates = detector.add(place_keyframe(index, 100 + index % 9))
        assert [c.score for c in candidates] == sorted((c.score for c in candidates), reverse=True)
        assert all(c.query == index and c.match < index - 3 for c in candidates)
        assert len(candidates) <= detector.config.max_candidates
    # Keyframe 12 revisits the place of keyframe 4 (place 104).
    candidates = detector.add(place_keyframe(12, 104))
    best = candidates[0]
    assert best.match == 4 and best.score == best.components["rf"]
    assert set(best.components) == {"vbow", "label_ratio", "hausdorff", "rf"}
    assert best.components["vbow"] == pytest.approx(1.0) and best.components["label_ratio"] == 1.0
    assert all(isinstance(v, float) for c in candidates for v in c.components.values())
    assert best.score >= detector.threshold


def test_featureless_and_objectless_keyframes() -> None:
    detector = create(["temporal_window=0"])
    assert detector.add(place_keyframe(0, 1, count=0)) == []
    assert detector.add(place_keyframe(1, 1, count=0)) == []  # never matched: too few features
    assert detector.add(place_keyframe(2, 2, count=10)) == []  # below min_features: no query
    assert detector.add(place_keyframe(3, 3, objects=())) == []  # only unmatchable keyframes before
    best = detector.add(place_keyframe(4, 3, objects=()))[0]
    assert best.match == 3 and best.components["label_ratio"] == 0.0
    assert best.components["hausdorff"] == NO_LAYOUT_HAUSDORFF
    # A keyframe without an image: the object filter sizes the image from the keypoints.
    assert detector.add(place_keyframe(5, 3, objects=(CHAIR,)))[0].match in (3, 4)


def test_deterministic_with_a_seed() -> None:
    keyframes = [place_keyframe(i, 200 + i % 7, (CHAIR, TV) if i % 2 else (CUP,)) for i in range(20)]
    runs = []
    for _ in range(2):
        detector = SymbioLCD(SymbioLCDConfig(seed=7, temporal_window=2), table=rule_table())
        runs.append([detector.add(k) for k in keyframes])
    assert runs[0] == runs[1] and any(runs[0])
    probe = rule_table(seed=1).features
    forests = [create([f"seed={seed}"]).forest for seed in (3, 3)]
    np.testing.assert_array_equal(forests[0].predict_proba(probe), forests[1].predict_proba(probe))


def test_config_is_validated() -> None:
    with pytest.raises(ConfigError, match="no_such_key"):
        create(["no_such_key=1"])
    for bad in ("shortlist=0", "max_candidates=0", "temporal_window=-1", "max_depth=-1"):
        with pytest.raises(ConfigError):
            create([bad])
    assert SymbioLCDConfig().temporal_window == 20 and SymbioLCDConfig().min_features == 20


def test_table_round_trip_and_bad_files(tmp_path: Path) -> None:
    good = tmp_path / "table.bin"  # any suffix: written as is
    table = rule_table()
    save_table(good, table, {"scenes": "unit", "seed": 0})
    loaded = load_table(good)
    np.testing.assert_allclose(loaded.features, table.features, rtol=1e-6)
    np.testing.assert_array_equal(loaded.labels, table.labels)
    assert create([f"model={good}"]).forest.n_features_in_ == len(FEATURE_NAMES)

    arrays = dict(np.load(good))
    variants = {
        "wrong_format": {"format": np.array("something-else")},
        "wrong_columns": {"feature_names": np.array(["a", "b", "c", "d", "e", "f"])},
        "one_class": {"labels": np.zeros_like(arrays["labels"])},
        "nan": {"features": np.where(arrays["features"] > 0.9, np.nan, arrays["features"])},
        "short_labels": {"labels": arrays["labels"][:-1]},
        "three_columns": {"features": arrays["features"][:, :3]},
    }
    bad_files = [tmp_path / "missing.npz"]
    for name, change in variants.items():
        path = tmp_path / f"{name}.npz"
        np.savez(path, **{**arrays, **change})
        bad_files.append(path)
    missing_key = tmp_path / "no_labels.npz"
    np.savez(missing_key, **{k: v for k, v in arrays.items() if k != "labels"})
    text = tmp_path / "text.npz"
    text.write_text("not a table")
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(good.read_bytes()[:100])
    bad_files += [missing_key, text, truncated]
    for bad in bad_files:
        with pytest.raises(InputFileError) as info:
            create([f"model={bad}"])
        assert str(bad) in str(info.value)


@pytest.fixture(scope="module")
def training_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A short 320x240 loop scene of a training seed (>= 100), rendered once."""
    folder = tmp_path_factory.mktemp("symbiolcd") / "train_loop"
    config = SynthConfig(
        seed=120, trajectory="loop", frames=300, width=320, height=240, fx=262.5, fy=262.5, cx=159.5, cy=119.5
    )
    write_scene(config, folder, progress=False)
    return folder


@pytest.mark.slow
def test_train_cli_and_revisits_of_a_synthetic_loop(
    training_scene: Path, small_loop_scene: Path, tmp_path: Path
) -> None:
    table_path, figures_path = tmp_path / "table.npz", tmp_path / "train.json"
    argv = ["symbiolcd-train", str(training_scene), "--out", str(table_path), "--json", str(figures_path)]
    assert symbio_main([*argv, "--miss-rate", "0.3", "--seed", "1"]) == 0
    figures = json.loads(figures_path.read_text())
    assert figures["positives"] > 0 and figures["negatives"] > 0
    assert (
        figures["pairs"] == figures["positives"] + figures["negatives"] == len(load_table(table_path).labels)
    )
    # Evaluation seeds are refused.
    assert symbio_main(["symbiolcd-train", str(small_loop_scene), "--out", str(tmp_path / "x.npz")]) == 2
    with pytest.raises(ConfigError, match="reserved for evaluation"):
        check_not_evaluation_scene(small_loop_scene)

    # The forest trained on seed 120 finds the revisits of the seed-3 scene.
    dataset = open_dataset(small_loop_scene)
    references: dict[int, list[int]] = {}
    for query, ref in read_loop_pairs(small_loop_scene / "gt_loop_pairs.txt").tolist():
        references.setdefault(query, []).append(ref)
    oracle = OBJECT_DETECTORS.load("oracle")(["miss_rate=0.3"])
    detector = create([f"model={table_path}"])
    frames: list[int] = []
    hits = loop_queries = 0
    for frame in (f for f in dataset if f.index % 6 == 0):
        keypoints, descriptors = extract_orb(frame.gray)
        objects = tuple(oracle.detect(frame.image, frame))
        keyframe = Keyframe(
            len(frames), frame.index, frame.timestamp, np.eye(4), keypoints, descriptors, objects, frame.image
        )
        candidates = detector.add(keyframe)
        frames.append(frame.index)
        if frame.index in references and candidates:
            loop_queries += 1
            best = frames[candidates[0].match]
            hits += any(abs(best - ref) <= 6 for ref in references[frame.index])
    assert loop_queries >= 10
    assert hits >= 0.9 * loop_queries
