"""The SymbioLCD2 detector: temporal constraint, windows, degenerate keyframes, backends, loops found."""

from __future__ import annotations

import math
import pickle
from pathlib import Path

import numpy as np
import pytest

from frontends.datasets import open_dataset
from frontends.errors import ConfigError
from frontends.gt_loops import read_loop_pairs
from frontends.orb import extract_orb
from frontends.types import DetectedObject, Keyframe
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS
from lcd.symbiolcd2 import SymbioLCD2, SymbioLCD2Config, create, temporal_penalty


def test_temporal_penalty_values() -> None:
    d = np.array([1.0, 10.0, 100.0])
    vanishing = temporal_penalty(d, alpha=2.0, beta=0.3, form="vanishing")
    np.testing.assert_allclose(vanishing, 2 * np.log1p(1 / (0.3 * d**2)))
    assert vanishing[0] == pytest.approx(2 * math.log(1 + 1 / 0.3))
    assert vanishing[2] < 1e-3 and np.all(np.diff(vanishing) < 0)  # large when close, vanishes far
    paper = temporal_penalty(d, alpha=2.0, beta=0.3, form="paper")
    np.testing.assert_allclose(paper, [2 * math.log(0.3), 2 * math.log(30.0), 2 * math.log(3000.0)])


#: The paper's kernel over the shipped tree's words: identical graphs score exactly 1. With the
#: defaults (online words, idf^2) a place seen once loses its words to the purge, and labels every
#: graph holds weigh 0, so the exact-kernel tests below pin these.
PAPER_KERNEL = ["vocabulary=", "idf_power=0"]


def _keyframe(index: int, seed: int, objects: tuple[DetectedObject, ...] = (), count: int = 300) -> Keyframe:
    rng = np.random.default_rng(seed)
    keypoints = rng.uniform(0, 320, size=(count, 2)).astype(np.float32)
    descriptors = rng.integers(0, 256, size=(count, 32), dtype=np.uint8)
    return Keyframe(index, index, float(index), np.eye(4), keypoints, descriptors, objects)


def test_window_components_and_revisit() -> None:
    detector = create([*PAPER_KERNEL, "temporal_window=3"])
    chair = (DetectedObject("chair", 0.9, (10, 10, 120, 150)), DetectedObject("tv", 0.8, (180, 20, 300, 100)))
    places = [100, 101, 102, 103, 104, 105, 106, 107]
    for index, place in enumerate(places):
        assert all(index - c.match > 3 for c in detector.add(_keyframe(index, place, chair)))
    # keyframe 8 revisits the place of keyframe 1: its best candidate, with a kernel of 1
    candidates = detector.add(_keyframe(8, 101, chair))
    assert candidates[0].match == 1
    best = candidates[0]
    assert best.components["wl"] == pytest.approx(1.0)
    assert best.score == pytest.approx(best.components["wl"] - best.components["temporal"])
    assert [c.score for c in candidates] == sorted((c.score for c in candidates), reverse=True)
    assert all(8 - c.match > 3 for c in candidates)


def test_release_frees_the_database_and_refuses_more_keyframes() -> None:
    detector = create([*PAPER_KERNEL, "temporal_window=3"])
    chair = (DetectedObject("chair", 0.9, (10, 10, 120, 150)),)
    for index in range(6):
        detector.add(_keyframe(index, 100 + index, chair))
    assert len(detector.kernel) == 6
    detector.release()
    assert len(detector.kernel) == 0
    with pytest.raises(RuntimeError, match="after release"):
        detector.add(_keyframe(6, 101, chair))


def test_featureless_keyframes_neither_query_nor_match() -> None:
    detector = create(["temporal_window=0"])
    assert detector.add(_keyframe(0, 1, count=0)) == []
    assert detector.add(_keyframe(1, 2, count=0)) == []  # two empty graphs would have a kernel of 1
    candidates = detector.add(_keyframe(2, 3))
    assert {c.match for c in candidates} == set()  # only featureless keyframes before it
    assert detector.add(_keyframe(3, 3))[0].match == 2


def test_keyframes_without_objects_are_counted_and_still_match() -> None:
    detector = create([*PAPER_KERNEL, "temporal_window=0"])
    detector.add(_keyframe(0, 5))
    assert detector.add(_keyframe(1, 5))[0].components["wl"] == pytest.approx(1.0)
    assert detector.object_poor_keyframes == 2


def test_grakel_backend_gives_the_same_scores() -> None:
    ours = create([*PAPER_KERNEL, "iterations=3"])
    reference = create([*PAPER_KERNEL, "iterations=3", "wl_backend=grakel"])
    objects = (
        DetectedObject("chair", 0.9, (10, 10, 120, 150)),
        DetectedObject("cup", 0.8, (200, 40, 260, 90)),
    )
    for index in range(14):
        keyframe = _keyframe(index, index % 5, objects if index % 2 else (), count=120)
        a, b = ours.add(keyframe), reference.add(keyframe)
        assert [c.match for c in a] == [c.match for c in b]
        np.testing.assert_allclose([c.score for c in a], [c.score for c in b], atol=1e-9)


def test_ablations_are_registered_and_config_is_validated() -> None:
    for name, tiers in (("symbiolcd2", 3), ("symbiolcd2-two-tier", 2), ("symbiolcd2-flat", 1)):
        detector = LOOP_DETECTORS.load(name)()
        assert isinstance(detector, SymbioLCD2) and detector.config.graph.tiers == tiers
        assert detector.name == name
    with pytest.raises(ConfigError, match="no_such_key"):
        create(["no_such_key=1"])
    with pytest.raises(ConfigError):
        create(["wl_backend=networkx"])
    with pytest.raises(ConfigError, match="idf_power"):
        create(["idf_power=3"])
    with pytest.raises(ConfigError, match="idf_power"):
        create(["idf_power=2", "wl_backend=grakel"])
    assert create(["idf_power=2"]).kernel.idf_power == 2  # type: ignore[union-attr]
    defaults = SymbioLCD2Config()
    assert (defaults.vocabulary, defaults.idf_power, defaults.proposal_threshold) == ("online", 2, 0.0)
    assert SymbioLCD2Config().iterations == 10 and SymbioLCD2Config().graph.margin_px == 25


def test_idf_kernel_survives_a_checkpoint() -> None:
    """A detector with the IDF kernel pickled mid-sequence answers as the uninterrupted one."""
    objects = (DetectedObject("chair", 0.9, (10, 10, 120, 150)),)
    keyframes = [_keyframe(i, i % 4, objects if i % 3 else (), count=120) for i in range(16)]
    detector = create(["idf_power=2", "temporal_window=2"])
    for keyframe in keyframes[:8]:
        detector.add(keyframe)
    resumed = pickle.loads(pickle.dumps(detector))
    for keyframe in keyframes[8:]:
        a, b = detector.add(keyframe), resumed.add(keyframe)
        assert [(c.match, c.score) for c in a] == [(c.match, c.score) for c in b]
        assert a


def test_finds_the_loops_of_a_synthetic_scene(small_loop_scene: Path) -> None:
    dataset = open_dataset(small_loop_scene)
    references: dict[int, list[int]] = {}
    for query, ref in read_loop_pairs(small_loop_scene / "gt_loop_pairs.txt").tolist():
        references.setdefault(query, []).append(ref)
    oracle = OBJECT_DETECTORS.load("oracle")(["miss_rate=0.3"])
    detector = create()
    frames: list[int] = []
    hits = loop_queries = 0
    for frame in (f for f in dataset if f.index % 5 == 0):
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
            hits += any(abs(best - ref) <= 5 for ref in references[frame.index])
    assert loop_queries >= 10
    assert hits >= 0.9 * loop_queries
    assert detector.object_poor_keyframes < len(frames)
