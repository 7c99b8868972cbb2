"""The online vocabulary (``lcd.online_vocabulary``): words, current IDF, purge, pickling, detectors."""

from __future__ import annotations

import io
import pickle
from pathlib import Path

import numpy as np
import pytest

from eval import checkpoint
from eval.checkpoint import FrameImages
from eval.lcd_eval import figures_of, run_lcd
from frontends.datasets import open_dataset
from frontends.errors import ConfigError
from frontends.gt_loops import read_loop_pairs
from frontends.orb import OrbConfig, extract_orb
from frontends.types import Keyframe
from lcd import symbiolcd2, vbow
from lcd.base import OBJECT_DETECTORS
from lcd.online_vocabulary import OnlineVocabulary, OnlineVocabularyConfig
from lcd.vocabulary import Vocabulary


def flip_bits(descriptors: np.ndarray, bits: int, rng: np.random.Generator) -> np.ndarray:
    """Each descriptor with ``bits`` distinct bits flipped."""
    unpacked = np.unpackbits(descriptors, axis=1)
    for row in unpacked:
        row[rng.choice(256, size=bits, replace=False)] ^= 1
    return np.packbits(unpacked, axis=1)


def landmark_stream(images: int, seed: int = 0) -> list[np.ndarray]:
    """Images that see a sliding window of random landmarks (each in three images, a few flipped
    bits per sighting) plus descriptors seen once."""
    rng = np.random.default_rng(seed)
    landmarks = rng.integers(0, 256, size=(20 * images + 60, 32), dtype=np.uint8)
    stream = []
    for k in range(images):
        seen = flip_bits(landmarks[20 * k : 20 * k + 60], 3, rng)
        once = rng.integers(0, 256, size=(15, 32), dtype=np.uint8)
        stream.append(np.concatenate([seen, once]))
    return stream


def dense_scores(
    history: list[np.ndarray], query: np.ndarray, live: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Reference: every image's TF-IDF vector over the live words under the IDF of all ``history``
    images, L1-normalised, and the L1 score of the ``query`` word ids (-1 = no word) against each."""
    size = len(live)
    counts = np.array([np.bincount(ids, minlength=size) for ids in history], dtype=np.float64)
    counts[:, ~live] = 0
    with np.errstate(divide="ignore"):
        idf = np.log(len(history) / (counts > 0).sum(axis=0))
    idf[~np.isfinite(idf)] = 0
    vectors = counts * idf
    vectors /= np.maximum(vectors.sum(axis=1, keepdims=True), 1e-300)
    q = np.bincount(query[query >= 0], minlength=size) * idf * live
    q = q / q.sum() if q.sum() > 0 else q
    return q, np.minimum(vectors, q).sum(axis=1)


@pytest.mark.parametrize("min_images", [2, 3])
def test_scores_use_the_current_idf_of_every_stored_image(min_images: int) -> None:
    """Incremental bookkeeping (A_d, purges) equals recomputing every vector from scratch."""
    vocabulary = OnlineVocabulary(OnlineVocabularyConfig(min_images=min_images))
    history: list[np.ndarray] = []
    stream = landmark_stream(14)
    for image in stream:
        founded, live = vocabulary.words_founded, vocabulary.live()
        bow, scores, ids = vocabulary.add_and_query(image)
        matched = np.where(ids < founded, ids, -1)
        if history:
            q, expected = dense_scores(history, matched, live)
            np.testing.assert_allclose(bow.weights, q[bow.words], rtol=1e-9)
            assert set(bow.words.tolist()) == set(np.flatnonzero(q).tolist())
            np.testing.assert_allclose(scores, expected, rtol=1e-9, atol=1e-12)
        history.append(ids)
    # Words seen once were purged; words of landmarks seen in three images were kept.
    assert 0 < vocabulary.size < vocabulary.words_founded
    # Every stored image against its own descriptors: its vector again (score 1), after purges.
    for k, image in enumerate(stream):
        scores = vocabulary.query(vocabulary.transform(image))
        _, expected = dense_scores(history, vocabulary.words(image), vocabulary.live())
        np.testing.assert_allclose(scores, expected, rtol=1e-9, atol=1e-12)
        assert scores[k] == pytest.approx(1.0)


def test_a_word_in_every_image_weighs_nothing_and_idf_follows_the_images_added() -> None:
    rng = np.random.default_rng(1)
    common, shared, rare = rng.integers(0, 256, size=(3, 1, 32), dtype=np.uint8)
    vocabulary = OnlineVocabulary(OnlineVocabularyConfig(min_images=1))

    def image(*parts: np.ndarray) -> np.ndarray:
        return np.concatenate([common, *parts, rng.integers(0, 256, size=(4, 32), dtype=np.uint8)])

    vocabulary.add(image(shared, rare))
    vocabulary.add(image(shared))
    for _ in range(4):
        vocabulary.add(image())
    # The common word is in all 6 images: idf ln(6/6) = 0, so a query of it alone has no vector.
    assert vocabulary.images == 6 and len(vocabulary.transform(common)) == 0
    query = np.concatenate([common, shared, rare])
    bow = vocabulary.transform(query)
    assert len(bow) == 2 and bow.weights.sum() == pytest.approx(1.0)
    # shared: idf ln(N / 2), rare: ln(N / 1), with N the images added so far.
    ratio = bow.weights[list(bow.words).index(vocabulary.words(shared)[0])] / bow.weights.max()
    assert ratio == pytest.approx(np.log(6 / 2) / np.log(6))
    for _ in range(4):
        vocabulary.add(image())
    bow = vocabulary.transform(query)
    ratio = bow.weights[list(bow.words).index(vocabulary.words(shared)[0])] / bow.weights.max()
    assert ratio == pytest.approx(np.log(10 / 2) / np.log(10))


def test_an_image_scores_itself_highest() -> None:
    stream = landmark_stream(12, seed=2)
    vocabulary = OnlineVocabulary()
    for image in stream:
        vocabulary.add(image)
    for k in (3, 6, 9):
        scores = vocabulary.query(vocabulary.transform(stream[k]))
        assert len(scores) == 12 and int(np.argmax(scores)) == k
        assert scores[k] > scores[k - 2] and scores[k] > scores[(k + 3) % 12]


def test_queries_see_earlier_images_only() -> None:
    stream = landmark_stream(3, seed=3)
    vocabulary = OnlineVocabulary()
    bow, scores, ids = vocabulary.add_and_query(stream[0])
    assert len(bow) == 0 and len(scores) == 0 and len(np.unique(ids)) == len(ids)
    bow, scores, _ = vocabulary.add_and_query(stream[0])  # the same image again: one earlier image
    assert scores.shape == (1,) and vocabulary.images == 2
    # Two images, both holding every matched word: idf 0, nothing to score yet.
    assert len(bow) == 0 and scores[0] == 0
    _, scores, _ = vocabulary.add_and_query(stream[1])
    assert scores.shape == (2,)
    empty = vocabulary.add_and_query(np.zeros((0, 32), np.uint8))
    assert len(empty[0]) == 0 and empty[1].shape == (3,) and vocabulary.images == 4


def test_nearest_word_within_max_distance_or_a_new_word() -> None:
    rng = np.random.default_rng(4)
    words = rng.integers(0, 256, size=(50, 32), dtype=np.uint8)
    vocabulary = OnlineVocabulary(OnlineVocabularyConfig(max_distance=40, min_images=1))
    first = vocabulary.add(words)
    np.testing.assert_array_equal(first, np.arange(50))
    near = flip_bits(words[:10], 6, rng)
    far = flip_bits(words[10:20], 41, rng)
    np.testing.assert_array_equal(vocabulary.words(near), np.arange(10))
    assert np.all(vocabulary.words(far) == -1)  # random words are ~128 bits from the others
    ids = vocabulary.add(np.concatenate([near, far]))
    np.testing.assert_array_equal(ids[:10], np.arange(10))
    np.testing.assert_array_equal(ids[10:], np.arange(50, 60))


def test_the_nearest_of_two_words_within_reach_wins() -> None:
    rng = np.random.default_rng(8)
    a = rng.integers(0, 256, size=(1, 32), dtype=np.uint8)
    differ = rng.choice(256, size=60, replace=False)
    bits_a = np.unpackbits(a, axis=1)
    bits_b = bits_a.copy()
    bits_b[0, differ] ^= 1
    # Many short keys: both words, 25 and 35 bits away, certainly share a key with the query.
    vocabulary = OnlineVocabulary(OnlineVocabularyConfig(tables=24, key_bits=8, min_images=1))
    np.testing.assert_array_equal(vocabulary.add(np.concatenate([a, np.packbits(bits_b, axis=1)])), [0, 1])
    for moved, nearest in ((25, 0), (35, 1), (30, 0)):  # a tie goes to the lower id
        query = bits_a.copy()
        query[0, differ[:moved]] ^= 1
        assert vocabulary.words(np.packbits(query, axis=1))[0] == nearest


def test_purge_deletes_words_not_seen_again() -> None:
    rng = np.random.default_rng(5)
    kept, lost = rng.integers(0, 256, size=(2, 8, 32), dtype=np.uint8)
    vocabulary = OnlineVocabulary(OnlineVocabularyConfig(min_images=2, purge_after=2))
    vocabulary.add(np.concatenate([kept, lost]))
    vocabulary.add(kept)
    assert vocabulary.size == 16  # not judged yet
    vocabulary.add(rng.integers(0, 256, size=(8, 32), dtype=np.uint8))
    live = vocabulary.live()
    assert live[:8].all() and not live[8:16].any()
    assert np.all(vocabulary.words(lost) == -1)
    np.testing.assert_array_equal(vocabulary.words(kept), np.arange(8))


def test_deterministic_and_pickles_to_an_identical_state() -> None:
    stream = landmark_stream(16, seed=6)
    a, b = OnlineVocabulary(), OnlineVocabulary()
    for image in stream[:10]:
        ra, rb = a.add_and_query(image), b.add_and_query(image)
        np.testing.assert_array_equal(ra[2], rb[2])
        np.testing.assert_array_equal(ra[1], rb[1])
    restored = pickle.loads(pickle.dumps(a))
    for image in stream[10:]:
        ra, rr = a.add_and_query(image), restored.add_and_query(image)
        np.testing.assert_array_equal(ra[0].words, rr[0].words)
        np.testing.assert_array_equal(ra[0].weights, rr[0].weights)  # bit for bit
        np.testing.assert_array_equal(ra[1], rr[1])
        np.testing.assert_array_equal(ra[2], rr[2])
    # Another seed samples other bits: the hash keys differ.
    other = OnlineVocabulary(OnlineVocabularyConfig(seed=1))
    assert not np.array_equal(other._index.positions, a._index.positions)


def test_a_detector_with_the_online_vocabulary_survives_a_checkpoint(tmp_path: Path) -> None:
    """Only numpy arrays and project classes: the checkpoint's allowlisted unpickler loads it."""
    detector = vbow.create(["vocabulary=online"])
    stream = landmark_stream(30, seed=7)
    for k, image in enumerate(stream[:25]):
        detector.add(Keyframe(k, k, float(k), np.eye(4), np.zeros((len(image), 2), np.float32), image))
    payload = pickle.dumps(detector, protocol=pickle.HIGHEST_PROTOCOL)
    path = tmp_path / "checkpoint-000025.pkl"
    restored = checkpoint._StateUnpickler(io.BytesIO(payload), None, FrameImages(), path).load()  # type: ignore[arg-type]
    for k, image in enumerate(stream[25:], start=25):
        keyframe = Keyframe(k, k, float(k), np.eye(4), np.zeros((len(image), 2), np.float32), image)
        assert detector.add(keyframe) == restored.add(keyframe)


def test_config_choices_and_validation() -> None:
    assert isinstance(vbow.open_vocabulary("online", OnlineVocabularyConfig()), OnlineVocabulary)
    assert isinstance(vbow.open_vocabulary("", OnlineVocabularyConfig()), Vocabulary)
    detector = symbiolcd2.create(["vocabulary=online", "online.max_distance=30"])
    assert isinstance(detector.vocabulary, OnlineVocabulary) and detector.vocabulary.config.max_distance == 30
    with pytest.raises(ConfigError, match="max_distance"):
        vbow.create(["vocabulary=online", "online.max_distance=300"])
    with pytest.raises(ConfigError, match="key_bits"):
        OnlineVocabularyConfig(tables=16, key_bits=29)
    with pytest.raises(ValueError, match="descriptors"):
        OnlineVocabulary().add(np.zeros((3, 16), np.uint8))


def test_vbow_and_symbiolcd2_find_synthetic_loops_with_the_online_vocabulary(small_loop_scene: Path) -> None:
    dataset = open_dataset(small_loop_scene)
    references: dict[int, list[int]] = {}
    for query, ref in read_loop_pairs(small_loop_scene / "gt_loop_pairs.txt").tolist():
        references.setdefault(query, []).append(ref)
    detectors = [vbow.create(["vocabulary=online"]), symbiolcd2.create(["vocabulary=online"])]
    frames: list[int] = []
    correct: dict[str, list[bool]] = {d.name: [] for d in detectors}
    for frame in (f for f in dataset if f.index % 5 == 0):
        keypoints, descriptors = extract_orb(frame.gray)
        keyframe = Keyframe(len(frames), frame.index, frame.timestamp, np.eye(4), keypoints, descriptors)
        for detector in detectors:
            candidates = detector.add(keyframe)
            if frame.index in references:
                best = frames[candidates[0].match] if candidates else -100
                correct[detector.name].append(any(abs(best - ref) <= 5 for ref in references[frame.index]))
        frames.append(frame.index)
    for name, hits in correct.items():
        assert len(hits) >= 10
        assert sum(hits) >= 0.8 * len(hits), (name, sum(hits), len(hits))
    assert isinstance(detectors[1].vocabulary, OnlineVocabulary) and detectors[1].vocabulary.size > 0


@pytest.mark.shared
def test_online_vocabulary_holds_on_the_rtabmap_samples(shared: Path) -> None:
    """``vbow``'s recall at 100 % precision (``symbio eval lcd``'s figure): online >= the shipped tree."""
    dataset = open_dataset(shared / "data" / "loops" / "rtabmap_samples")
    detectors = [vbow.create(["vocabulary=online"]), vbow.create(["vocabulary="])]
    objects = OBJECT_DETECTORS.load("none")([])
    runs = run_lcd(dataset, detectors, objects, OrbConfig(), 0.2, 0, False)
    online, tree = (figures_of(run, 0.1)["recall_at_100p"] for run in runs)
    assert online >= tree and online >= 0.95, (online, tree)
