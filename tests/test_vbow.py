"""Vocabulary tree, BoW scoring, inverted index, ORB extraction and the ``vbow`` loop detector."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from eval.cli import main as symbio_main
from frontends.datasets import open_dataset
from frontends.errors import ConfigError, InputFileError
from frontends.gt_loops import read_loop_pairs
from frontends.orb import OrbConfig, detect_orb, extract_orb
from frontends.synth import SynthConfig, write_scene
from frontends.types import Keyframe
from lcd.base import LOOP_DETECTORS, LoopDetector
from lcd.vbow import VbowConfig, VbowDetector, create
from lcd.vocabulary import BowDatabase, BowVector, Vocabulary, empty_bow, hamming, l1_score


def clustered_descriptors(seed: int, images: int = 12, per_image: int = 150) -> list[np.ndarray]:
    """Descriptors near 40 random prototypes (a few flipped bits), like repeated visual patterns."""
    rng = np.random.default_rng(seed)
    prototypes = rng.integers(0, 256, size=(40, 32), dtype=np.uint8)
    out = []
    for _ in range(images):
        base = prototypes[rng.integers(len(prototypes), size=per_image)]
        noise = np.packbits(rng.random((per_image, 256)) < 0.03, axis=1)
        out.append(base ^ noise)
    return out


@pytest.fixture(scope="module")
def small_vocabulary() -> Vocabulary:
    vocabulary, _ = Vocabulary.train(clustered_descriptors(0), k=4, levels=3, seed=7)
    return vocabulary


def bow(words: list[int], weights: list[float]) -> BowVector:
    w = np.asarray(weights, dtype=np.float64)
    return BowVector(np.asarray(words, dtype=np.int64), w / w.sum())


# -- vocabulary --------------------------------------------------------------------------------------


def test_hamming_matches_bit_count() -> None:
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (7, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (5, 32), dtype=np.uint8)
    expected = np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(axis=2)
    np.testing.assert_array_equal(hamming(a, b), expected)


def test_training_is_deterministic_given_a_seed() -> None:
    data = clustered_descriptors(3)
    first, stats = Vocabulary.train(data, k=4, levels=3, seed=11)
    second, _ = Vocabulary.train(data, k=4, levels=3, seed=11)
    for a, b in zip([*first.centroids, *first.parents], [*second.centroids, *second.parents], strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(first.idf, second.idf)
    assert stats.images == len(data) and stats.descriptors == sum(len(d) for d in data)
    assert stats.words == first.size <= 4**3
    _, capped_stats = Vocabulary.train(data, k=4, levels=3, seed=11, max_descriptors=500)
    assert capped_stats.descriptors == 500


def test_tree_structure_and_idf(small_vocabulary: Vocabulary) -> None:
    v = small_vocabulary
    assert v.levels == 3 and v.k == 4
    for level, parents in enumerate(v.parents):
        counts = np.bincount(parents, minlength=1 if level == 0 else len(v.centroids[level - 1]))
        assert counts.min() >= 1 and counts.max() <= v.k
    # IDF = ln(N / n_i) over the training images.
    images = clustered_descriptors(0)
    seen = np.zeros(v.size)
    for d in images:
        seen[np.unique(v.paths(d)[:, -1])] += 1
    expected = np.where(seen > 0, np.log(len(images) / np.maximum(seen, 1)), 0.0)
    np.testing.assert_allclose(v.idf, expected)


def test_words_at_level_follow_the_tree(small_vocabulary: Vocabulary) -> None:
    v = small_vocabulary
    descriptors = clustered_descriptors(5, images=1, per_image=300)[0]
    paths = v.paths(descriptors)
    for level in range(1, v.levels + 1):
        words = v.words_at_level(descriptors, level)
        np.testing.assert_array_equal(words, paths[:, level - 1])
        assert words.max() < len(v.centroids[level - 1])
        if level > 1:  # each word's parent is the word one level up
            np.testing.assert_array_equal(v.parents[level - 1][words], paths[:, level - 2])
    # Greedy descent: at every level the chosen node is the nearest of its siblings.
    for i in range(0, len(descriptors), 37):
        parent = 0
        for level in range(v.levels):
            siblings = np.flatnonzero(v.parents[level] == parent)
            distance = hamming(descriptors[i : i + 1], v.centroids[level][siblings])[0]
            assert distance[np.searchsorted(siblings, paths[i, level])] == distance.min()
            parent = paths[i, level]
    with pytest.raises(ValueError):
        v.words_at_level(descriptors, 0)
    with pytest.raises(ValueError):
        v.words_at_level(descriptors, v.levels + 1)


def test_l1_score_known_answers(small_vocabulary: Vocabulary) -> None:
    a = bow([0, 1, 2], [0.5, 0.3, 0.2])
    b = bow([1, 2, 3], [0.2, 0.2, 0.6])
    # 1 - 0.5 * (|0.5 - 0| + |0.3 - 0.2| + |0.2 - 0.2| + |0 - 0.6|) = 0.4
    assert l1_score(a, b) == pytest.approx(0.4)
    assert l1_score(a, a) == pytest.approx(1.0)
    assert l1_score(a, bow([5, 6], [1, 1])) == 0.0
    assert l1_score(a, empty_bow()) == 0.0
    descriptors = clustered_descriptors(9, images=2)
    v1, v2 = (small_vocabulary.transform(d) for d in descriptors)
    assert l1_score(v1, v1) == pytest.approx(1.0)
    assert v1.weights.sum() == pytest.approx(1.0) and np.all(np.diff(v1.words) > 0)
    # The inverted-index form (sum of minima) equals the DBoW2 L1 formula on dense vectors.
    dense = np.zeros((2, small_vocabulary.size))
    dense[0, v1.words], dense[1, v2.words] = v1.weights, v2.weights
    assert l1_score(v1, v2) == pytest.approx(1 - 0.5 * np.abs(dense[0] - dense[1]).sum())
    # TF-IDF: weight of word i ~ (count_i / N) * idf_i.
    leaves = small_vocabulary.paths(descriptors[0])[:, -1]
    raw = np.bincount(leaves, minlength=small_vocabulary.size) / len(leaves) * small_vocabulary.idf
    np.testing.assert_allclose(dense[0], raw / raw.sum())
    assert len(small_vocabulary.transform(np.zeros((0, 32), np.uint8))) == 0


def test_database_query_equals_pairwise_scores() -> None:
    rng = np.random.default_rng(2)
    vectors = []
    for i in range(37):
        words = np.unique(rng.integers(0, 60, size=rng.integers(1, 25)))
        vectors.append(empty_bow() if i == 5 else bow(words.tolist(), rng.random(len(words)).tolist()))
    database = BowDatabase()
    for index, vector in enumerate(vectors):
        assert database.add(vector) == index
    assert len(database) == len(vectors)
    for query in vectors[:8]:
        expected = [l1_score(query, v) for v in vectors]
        np.testing.assert_allclose(database.query(query), expected, atol=1e-12)
    np.testing.assert_array_equal(BowDatabase().query(vectors[0]), np.zeros(0))


def test_save_load_round_trip_and_bad_files(small_vocabulary: Vocabulary, tmp_path: Path) -> None:
    path = tmp_path / "voc.npz"
    small_vocabulary.save(path)
    loaded = Vocabulary.load(path)
    descriptors = clustered_descriptors(4, images=1)[0]
    np.testing.assert_array_equal(loaded.paths(descriptors), small_vocabulary.paths(descriptors))
    np.testing.assert_allclose(loaded.idf, small_vocabulary.idf, rtol=1e-6)
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    wrong = tmp_path / "wrong.npz"
    np.savez(wrong, a=np.zeros(3))
    inconsistent = tmp_path / "inconsistent.npz"
    arrays = dict(np.load(path))
    arrays["parents_2"] = arrays["parents_2"][::-1].copy()
    np.savez(inconsistent, **arrays)
    text = tmp_path / "text.npz"
    text.write_text("hello")
    for bad in (corrupt, wrong, inconsistent, text, tmp_path / "missing.npz"):
        with pytest.raises(InputFileError) as info:
            Vocabulary.load(bad)
        assert str(bad) in str(info.value)


# -- features ----------------------------------------------------------------------------------------


def textured_image(seed: int, width: int = 320, height: int = 240) -> np.ndarray:
    rng = np.random.default_rng(seed)
    image = cv2.resize(rng.integers(0, 256, (height // 8, width // 8), dtype=np.uint8), (width, height))
    for _ in range(40):
        x, y = (int(v) for v in rng.integers(0, [width, height]))
        cv2.rectangle(image, (x, y), (x + 20, y + 15), int(rng.integers(0, 256)), -1)
    return image


def test_extract_orb_shapes_budget_and_empty_images() -> None:
    gray = textured_image(0)
    keypoints, descriptors = extract_orb(gray)
    budget = OrbConfig().features_for(320, 240)
    assert budget == 500  # the floor: a quarter of 640x480 would be 250
    assert keypoints.dtype == np.float32 and keypoints.shape[1] == 2
    assert descriptors.dtype == np.uint8 and descriptors.shape == (len(keypoints), 32)
    assert 0 < len(keypoints) <= budget
    features = detect_orb(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR), OrbConfig(grid_cols=4, grid_rows=3))
    assert 0 < len(features.keypoints) <= budget
    assert len(features.sizes) == len(features.angles) == len(features.octaves) == len(features.keypoints)
    for blank in (np.zeros((240, 320), np.uint8), np.zeros((10, 10), np.uint8)):
        k, d = extract_orb(blank)
        assert k.shape == (0, 2) and d.shape == (0, 32)
    with pytest.raises(ValueError):
        extract_orb(np.zeros((20, 20), np.float32))


# -- detector ----------------------------------------------------------------------------------------


def keyframe(index: int, descriptors: np.ndarray, timestamp: float | None = None) -> Keyframe:
    return Keyframe(
        index, index, float(index) if timestamp is None else timestamp, np.eye(4), descriptors=descriptors
    )


def test_detector_windows_empty_keyframes_and_config(small_vocabulary: Vocabulary) -> None:
    images = clustered_descriptors(8, images=30)
    detector = VbowDetector(VbowConfig(temporal_window=4, max_candidates=50), small_vocabulary)
    assert LOOP_DETECTORS.load("vbow") is create and isinstance(detector, LoopDetector)
    assert detector.add(keyframe(0, np.zeros((0, 32), np.uint8))) == []
    for i in range(1, 30):
        candidates = detector.add(keyframe(i, images[i]))
        assert all(c.match <= i - 5 and c.query == i for c in candidates)
        assert [c.score for c in candidates] == sorted((c.score for c in candidates), reverse=True)
        assert all(c.components["vbow"] == c.score for c in candidates)
    # A revisit of keyframe 3's descriptors finds it first with score 1.
    best = detector.add(keyframe(30, images[3]))[0]
    assert (best.match, best.score) == (3, pytest.approx(1.0))
    assert detector.add(keyframe(31, np.zeros((0, 32), np.uint8))) == []
    timed = VbowDetector(VbowConfig(temporal_window=0, time_window=10.0), small_vocabulary)
    for i in range(20):
        assert all(c.match <= i - 10 for c in timed.add(keyframe(i, images[i])))
    with pytest.raises(ConfigError):
        create(["temporal_window=-1"])
    with pytest.raises(ConfigError):
        create(["normalise=orbslam"])


def test_normalisation_and_consistency(small_vocabulary: Vocabulary) -> None:
    images = clustered_descriptors(8, images=16)
    normalised = VbowDetector(VbowConfig(temporal_window=2, normalise="previous"), small_vocabulary)
    consistent = VbowDetector(VbowConfig(temporal_window=2, consistency=2, threshold=0.0), small_vocabulary)
    for i in range(16):
        for c in normalised.add(keyframe(i, images[i])):
            assert c.score == pytest.approx(c.components["normalised"])
        candidates = consistent.add(keyframe(i, images[i]))
        # The first two queries with candidates (positions 3 and 4) cannot be consistent yet.
        if i < 5:
            assert candidates == []
        assert all(c.components["consistency"] >= 2 for c in candidates)


@pytest.fixture(scope="module")
def loop_scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("vbow") / "scene"
    config = SynthConfig(
        seed=3, trajectory="loop", frames=300, width=320, height=240, fx=262.5, fy=262.5, cx=159.5, cy=119.5
    )
    write_scene(config, folder, progress=False)
    return folder


def test_default_detector_finds_synthetic_loops(loop_scene: Path) -> None:
    dataset = open_dataset(loop_scene)
    pairs = read_loop_pairs(loop_scene / "gt_loop_pairs.txt")
    references: dict[int, set[int]] = {}
    for query, ref in pairs.tolist():
        references.setdefault(query, set()).add(ref)
    detector = create()
    hits, loop_queries = 0, 0
    for kf_id, frame in enumerate(f for f in dataset if f.index % 5 == 0):
        keypoints, descriptors = extract_orb(frame.gray)
        candidates = detector.add(
            Keyframe(kf_id, frame.index, frame.timestamp, np.eye(4), keypoints, descriptors)
        )
        if frame.index in references:
            loop_queries += 1
            best = 5 * candidates[0].match if candidates else -100
            # Near a GT reference: within one keyframe step of one.
            hits += any(abs(best - ref) <= 5 for ref in references[frame.index])
    assert loop_queries >= 10
    assert hits >= 0.9 * loop_queries


def test_vocab_train_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    images = tmp_path / "images"
    images.mkdir()
    for i in range(4):
        cv2.imwrite(str(images / f"{i:03d}.png"), textured_image(i))
    single = tmp_path / "single.png"
    cv2.imwrite(str(single), textured_image(9))
    outputs = []
    for run in range(2):
        out, figures = tmp_path / f"v{run}.npz", tmp_path / f"v{run}.json"
        argv = ["vocab", "train", str(images), str(single), "--k", "4", "--levels", "3", "--seed", "5"]
        assert symbio_main([*argv, "--out", str(out), "--json", str(figures)]) == 0
        outputs.append(Vocabulary.load(out))
    result = json.loads(figures.read_text())
    assert result["images"] == 5 and result["words"] == outputs[0].size and result["seconds"] >= 0
    assert "descriptors" in capsys.readouterr().out
    for a, b in zip(outputs[0].centroids, outputs[1].centroids, strict=True):
        np.testing.assert_array_equal(a, b)
    assert symbio_main(["vocab", "train", str(tmp_path / "nothing"), "--out", str(tmp_path / "x.npz")]) == 2


# -- shared data -------------------------------------------------------------------------------------


def recall_at_full_precision(best: list[tuple[float, bool]], loop_queries: int) -> float:
    """Max recall with precision 1 when sweeping a threshold over each query's best score."""
    ordered = sorted(best, key=lambda item: -item[0])
    accepted = 0
    for score, correct in ordered:
        if not correct:
            # Every candidate scoring as high as this false positive goes with it.
            accepted = sum(1 for s, c in ordered[:accepted] if s > score and c)
            break
        accepted += 1
    return accepted / loop_queries


@pytest.mark.shared
def test_rtabmap_samples_recall(shared: Path) -> None:
    root = shared / "data" / "loops" / "rtabmap_samples"
    dataset = open_dataset(root)
    pairs = {tuple(p) for p in read_loop_pairs(root / "gt_loop_pairs.txt").tolist()}
    detector = create()
    best = []
    for frame in dataset:
        keypoints, descriptors = extract_orb(frame.gray)
        candidates = detector.add(
            Keyframe(frame.index, frame.index, frame.timestamp, np.eye(4), keypoints, descriptors)
        )
        if candidates:
            best.append((candidates[0].score, (frame.index, candidates[0].match) in pairs))
    loop_queries = len({q for q, _ in pairs})
    recall = recall_at_full_precision(best, loop_queries)
    assert recall >= 0.85, recall
