"""An incremental binary bag of words, built online from the sequence (iBoW-LCD / OBIndex2 style).

No training set: the words are ORB descriptors of the sequence itself (Garcia-Fidalgo & Ortiz,
iBoW-LCD, RA-L 2018). Each added image's descriptors are matched to the words so far: a descriptor
joins its nearest live word when that lies within ``max_distance`` bits, otherwise it founds a new
word (the word keeps its founding descriptor, like iBoW-LCD's default "no merge" policy). A word
seen in fewer than ``min_images`` images by the time ``purge_after`` more images have been added is
deleted (OBIndex2's purge of unstable features): it keeps the word set, and the time to search it,
to the features that are seen again.

Weights: TF-IDF with the IDF of the images added so far, ``ln(N / n_i)``, N images added, n_i of
them with word i (a word in every image weighs 0). Stored images are never frozen with an old IDF:
the score of a query against image d uses d's vector under the *current* IDF,
``d_i = c_di (ln N - ln n_i) / Z_d`` with ``Z_d = S_d ln N - A_d``, ``S_d`` the descriptor count of
d's live words and ``A_d = sum_i c_di ln n_i``, which is kept up to date as n_i grows (each added
image updates A of the images that share its words, the same postings a query reads). Vectors are
L1-normalised and compared with DBoW2's L1 score ``sum_i min(q_i, d_i)``, as ``lcd.vocabulary``.

Nearest-word search: a locality-sensitive hash (``tables`` keys of ``key_bits`` sampled bits each,
bit positions drawn from ``seed``) finds the words sharing a key with the descriptor in some table,
and the nearest of those (ties: the lowest word id) is taken, with its exact Hamming distance. It is
approximate: a word it misses makes the descriptor found a duplicate word. The hash tables are
log-structured sorted runs (each image's new words are a run; a run at least as long as the one
before it is merged into it), so adding is amortised O(log n) per word and one search is a few
``searchsorted`` calls per run. OpenCV's FLANN LSH is not used: it draws its bit positions from
OpenCV's global RNG. The runs are not pickled but rebuilt from the words (candidates do not depend
on the run layout); everything else is plain numpy arrays, pickled as is so that a resumed run
scores bit for bit alike.

Word ids are stable and never reused (a purged word's id stays dead), so they serve as graph labels
(``lcd.graph`` keeps 24 bits of a label's word: ids alias after 2**24 founded words, ~16 000
keyframes of 1 000 descriptors). Defaults and measurements: docs/2026-12-06-online-vocabulary.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from frontends.errors import ConfigError
from lcd.vocabulary import DESCRIPTOR_BYTES, BowVector, empty_bow

#: Bits per descriptor.
_BITS = 8 * DESCRIPTOR_BYTES
#: Combined sort keys ``descriptor << 40 | distance << 31 | word``: word ids stay below 2**31.
_DESCRIPTOR_SHIFT = 40
_DISTANCE_SHIFT = 31
#: Descriptors per block of a key computation (bounds the (block, tables, key_bits) temporary).
_KEY_BLOCK = 1 << 14


@dataclass(frozen=True)
class OnlineVocabularyConfig:
    #: A descriptor joins its nearest word when at most this many bits (of 256) differ, else founds one.
    max_distance: int = 40
    #: A word seen in fewer images than this once ``purge_after`` more images were added is deleted.
    min_images: int = 2
    #: Images after a word's founding image at which the ``min_images`` test is made.
    purge_after: int = 2
    #: Hash tables of the nearest-word search (more: fewer missed neighbours, slower).
    tables: int = 16
    #: Sampled bits per hash key (more: smaller buckets, fewer candidates, more missed neighbours).
    key_bits: int = 16
    #: Seed of the sampled bit positions.
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0 <= self.max_distance <= _BITS:
            raise ConfigError(f"online vocabulary: max_distance must be in 0..{_BITS}")
        if self.min_images < 1 or self.purge_after < 1 or self.tables < 1:
            raise ConfigError("online vocabulary: min_images, purge_after and tables must be >= 1")
        # Table index and key share one uint32 sort key.
        if not 1 <= self.key_bits <= 32 - max(1, int(self.tables - 1).bit_length()):
            raise ConfigError("online vocabulary: key_bits must be >= 1 and fit 32 bits with the table index")


class _Rows:
    """An append-only numpy array (rows along axis 0) with amortised O(1) appends."""

    def __init__(self, dtype: Any, shape: tuple[int, ...] = ()) -> None:
        self._data: np.ndarray = np.zeros((16, *shape), dtype=dtype)
        self._size = 0

    def __len__(self) -> int:
        return self._size

    def extend(self, values: np.ndarray) -> None:
        end = self._size + len(values)
        if end > len(self._data):
            grown = np.zeros((max(end, 2 * len(self._data)), *self._data.shape[1:]), dtype=self._data.dtype)
            grown[: self._size] = self._data[: self._size]
            self._data = grown
        self._data[self._size : end] = values
        self._size = end

    def view(self) -> np.ndarray:
        return self._data[: self._size]

    def __getstate__(self) -> dict[str, Any]:
        """Pickles the used part only."""
        return {"data": self.view()}

    def __setstate__(self, state: dict[str, Any]) -> None:
        data = np.asarray(state["data"])
        self._data = np.zeros((max(16, 2 * len(data)), *data.shape[1:]), dtype=data.dtype)
        self._data[: len(data)] = data
        self._size = len(data)


def _ranges(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(which range, position) of every element of the concatenated ranges ``[lo_i, hi_i)``."""
    lengths = hi - lo
    owner = np.repeat(np.arange(len(lo), dtype=np.int64), lengths)
    starts = np.cumsum(lengths) - lengths
    return owner, np.repeat(lo - starts, lengths) + np.arange(int(lengths.sum()), dtype=np.int64)


class _Postings:
    """The inverted index: (word, image, count) postings in word-sorted blocks, merged by image count
    like an LSM tree (as ``lcd.vocabulary.BowDatabase``); dead words' postings go at merges."""

    def __init__(self) -> None:
        # (words, images, counts, images in the block); image counts are powers of two, largest first.
        self.blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []

    def add(self, words: np.ndarray, image: int, counts: np.ndarray, alive: np.ndarray) -> None:
        self.blocks.append((words, np.full(len(words), image, dtype=np.int32), counts, 1))
        while len(self.blocks) >= 2 and self.blocks[-1][3] == self.blocks[-2][3]:
            right, left = self.blocks.pop(), self.blocks.pop()
            merged_words = np.concatenate([left[0], right[0]])
            keep = alive[merged_words]
            order = np.argsort(merged_words[keep], kind="stable")
            self.blocks.append(
                (
                    merged_words[keep][order],
                    np.concatenate([left[1], right[1]])[keep][order],
                    np.concatenate([left[2], right[2]])[keep][order],
                    left[3] + right[3],
                )
            )

    def gather(self, words: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every posting of the sorted unique ``words``: (index into ``words``, image, count)."""
        owners, images, counts = [], [], []
        for block_words, block_images, block_counts, _ in self.blocks:
            lo = np.searchsorted(block_words, words, side="left")
            hi = np.searchsorted(block_words, words, side="right")
            owner, position = _ranges(lo, hi)
            owners.append(owner)
            images.append(block_images[position])
            counts.append(block_counts[position])
        if not owners:
            return np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0, np.int32)
        return np.concatenate(owners), np.concatenate(images), np.concatenate(counts)


class _HashIndex:
    """Bit-sampling LSH over the words: log-structured runs of (table << key_bits | key, word) sorted."""

    def __init__(self, config: OnlineVocabularyConfig) -> None:
        rng = np.random.default_rng(config.seed)
        self.key_bits = config.key_bits
        #: (tables, key_bits) sampled bit positions, distinct within a table.
        self.positions = np.stack([rng.permutation(_BITS)[: config.key_bits] for _ in range(config.tables)])
        self.runs: list[tuple[np.ndarray, np.ndarray]] = []

    def keys(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, tables) uint32 keys, the table index in the high bits."""
        tables = len(self.positions)
        out = np.empty((len(descriptors), tables), dtype=np.uint32)
        weights = np.left_shift(np.uint32(1), np.arange(self.key_bits, dtype=np.uint32))
        offsets = np.arange(tables, dtype=np.uint32) << np.uint32(self.key_bits)
        for start in range(0, len(descriptors), _KEY_BLOCK):
            bits = np.unpackbits(descriptors[start : start + _KEY_BLOCK], axis=1)
            sampled = bits[:, self.positions].astype(np.uint32)
            out[start : start + _KEY_BLOCK] = (sampled * weights).sum(axis=2, dtype=np.uint32) | offsets
        return out

    def insert(self, descriptors: np.ndarray, ids: np.ndarray, alive: np.ndarray) -> None:
        """Hash the words ``ids`` (their ``descriptors``) as one new run, then merge runs as needed."""
        if len(descriptors) == 0:
            return
        keys = self.keys(descriptors)
        words = np.repeat(ids.astype(np.int32), keys.shape[1])
        order = np.argsort(keys.ravel(), kind="stable")
        self.runs.append((keys.ravel()[order], words[order]))
        while len(self.runs) >= 2 and len(self.runs[-1][0]) >= len(self.runs[-2][0]):
            right, left = self.runs.pop(), self.runs.pop()
            keys_merged = np.concatenate([left[0], right[0]])
            words_merged = np.concatenate([left[1], right[1]])
            keep = alive[words_merged]
            order = np.argsort(keys_merged[keep], kind="stable")
            self.runs.append((keys_merged[keep][order], words_merged[keep][order]))

    def candidates(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(descriptor index, word id) of every word sharing a key with a descriptor (repeats possible)."""
        # Sorted needles make ``searchsorted`` several times faster (each search starts at the last).
        order = np.argsort(keys.ravel())
        flat = keys.ravel()[order]
        owners, words = [], []
        for run_keys, run_words in self.runs:
            lo = np.searchsorted(run_keys, flat, side="left")
            hi = np.searchsorted(run_keys, flat, side="right")
            owner, position = _ranges(lo, hi)
            owners.append(order[owner] // keys.shape[1])
            words.append(run_words[position])
        if not owners:
            return np.zeros(0, np.int64), np.zeros(0, np.int32)
        return np.concatenate(owners), np.concatenate(words)


class OnlineVocabulary:
    """Words and inverted index grown from the images added so far; see the module docstring.

    For a loop detector: ``add_and_query`` scores an image against the earlier images, then adds it.
    """

    def __init__(self, config: OnlineVocabularyConfig = OnlineVocabularyConfig()) -> None:
        self.config = config
        self._words = _Rows(np.uint8, (DESCRIPTOR_BYTES,))
        #: Per word: images it occurs in, whether it is live.
        self._images_with = _Rows(np.int64)
        self._alive = _Rows(bool)
        #: Per image: its first word id (words founded by an image are consecutive), S_d and A_d.
        self._first_word = _Rows(np.int64)
        self._mass = _Rows(np.float64)
        self._log_mass = _Rows(np.float64)
        self._postings = _Postings()
        self._index = _HashIndex(config)

    # -- sizes ----------------------------------------------------------------------------------

    @property
    def images(self) -> int:
        """N, the images added so far."""
        return len(self._mass)

    @property
    def size(self) -> int:
        """The number of live words."""
        return int(self._alive.view().sum())

    @property
    def words_founded(self) -> int:
        """Every word ever founded, purged ones included (word ids lie below this)."""
        return len(self._words)

    def live(self) -> np.ndarray:
        """(words_founded,) whether each word id is live (not purged)."""
        return self._alive.view().copy()

    # -- words ----------------------------------------------------------------------------------

    def words(self, descriptors: np.ndarray) -> np.ndarray:
        """(N,) id of each descriptor's nearest live word within ``max_distance``; -1 where none is."""
        d = _checked(descriptors)
        if len(d) == 0 or len(self._words) == 0:
            return np.full(len(d), -1, dtype=np.int64)
        owner, candidate = self._index.candidates(self._index.keys(d))
        alive = self._alive.view()[candidate]
        owner, candidate = owner[alive], candidate[alive].astype(np.int64)
        best = np.full(len(d), -1, dtype=np.int64)
        if len(owner) == 0:
            return best
        words64 = self._words.view().view(np.uint64)
        distance = np.bitwise_count(words64[candidate] ^ d.view(np.uint64)[owner]).sum(axis=1, dtype=np.int64)
        combined = (owner << _DESCRIPTOR_SHIFT) | (distance << _DISTANCE_SHIFT) | candidate
        lowest = np.full(len(d), np.iinfo(np.int64).max, dtype=np.int64)
        np.minimum.at(lowest, owner, combined)
        found = lowest != np.iinfo(np.int64).max
        nearest = lowest[found] & ((1 << _DISTANCE_SHIFT) - 1)
        within = (lowest[found] >> _DISTANCE_SHIFT) & ((1 << (_DESCRIPTOR_SHIFT - _DISTANCE_SHIFT)) - 1)
        best[np.flatnonzero(found)] = np.where(within <= self.config.max_distance, nearest, -1)
        return best

    # -- vectors and scores -----------------------------------------------------------------------

    def transform(self, descriptors: np.ndarray) -> BowVector:
        """The L1-normalised TF-IDF vector of descriptors against the current words and IDF."""
        return self._bow(self.words(descriptors))

    def _bow(self, ids: np.ndarray) -> BowVector:
        ids = ids[ids >= 0]
        if len(ids) == 0:
            return empty_bow()
        words, counts = np.unique(ids, return_counts=True)
        weights = counts * (np.log(self.images) - np.log(self._images_with.view()[words]))
        keep = weights > 0
        total = weights[keep].sum()
        if total <= 0:
            return empty_bow()
        return BowVector(words[keep].astype(np.int64), weights[keep] / total)

    def query(self, bow: BowVector) -> np.ndarray:
        """L1 scores of ``bow`` against every added image under the current IDF, indexed by image."""
        owner, images, counts = self._postings.gather(bow.words)
        return self._scores(bow, owner, images, counts)

    def _scores(
        self, bow: BowVector, owner: np.ndarray, images: np.ndarray, counts: np.ndarray
    ) -> np.ndarray:
        if len(owner) == 0:
            return np.zeros(self.images, dtype=np.float64)
        log_n = np.log(self.images)
        norm = self._mass.view() * log_n - self._log_mass.view()
        # An image whose every word is in every image has no weight left (norm 0): score 0.
        valid = norm[images] > 1e-12
        owner, images, counts = owner[valid], images[valid], counts[valid]
        idf = log_n - np.log(self._images_with.view()[bow.words])
        stored = counts * idf[owner] / norm[images]
        shared = np.minimum(bow.weights[owner], stored)
        return np.bincount(images, weights=shared, minlength=self.images)

    # -- growth ---------------------------------------------------------------------------------

    def add(self, descriptors: np.ndarray) -> np.ndarray:
        """Add one image: (N,) word id of each descriptor, founding new words for the unmatched."""
        return self.add_and_query(descriptors, score=False)[2]

    def add_and_query(
        self, descriptors: np.ndarray, score: bool = True
    ) -> tuple[BowVector, np.ndarray, np.ndarray]:
        """One image: its vector against the words so far, its L1 scores against every earlier image
        (zeros without ``score``), then it is added; the third item is each descriptor's word id."""
        d = _checked(descriptors)
        ids = self.words(d)
        bow = self._bow(ids)
        # The postings of every existing word of the image: for the scores and for the A_d update.
        existing = np.unique(ids[ids >= 0])
        owner, images, counts = self._postings.gather(existing)
        scores = np.zeros(self.images, dtype=np.float64)
        if score:
            scores = self._scores(bow, *self._restrict(bow, existing, owner, images, counts))
        new = ids < 0
        first = len(self._words)
        ids[new] = first + np.arange(int(new.sum()))
        self._found(d[new], first)
        self._insert_image(ids, existing, owner, images, counts, first)
        self._purge()
        return bow, scores, ids

    @staticmethod
    def _restrict(
        bow: BowVector, existing: np.ndarray, owner: np.ndarray, images: np.ndarray, counts: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The gathered postings of ``existing`` re-indexed by ``bow.words`` (a subset of it)."""
        position = np.searchsorted(bow.words, existing)
        inside = position < len(bow.words)
        inside[inside] = bow.words[position[inside]] == existing[inside]
        keep = inside[owner]
        return position[owner[keep]], images[keep], counts[keep]

    def _found(self, descriptors: np.ndarray, first: int) -> None:
        self._words.extend(descriptors)
        self._images_with.extend(np.zeros(len(descriptors), dtype=np.int64))
        self._alive.extend(np.ones(len(descriptors), dtype=bool))
        ids = np.arange(first, first + len(descriptors), dtype=np.int64)
        self._index.insert(descriptors, ids, self._alive.view())

    def _insert_image(
        self,
        ids: np.ndarray,
        existing: np.ndarray,
        owner: np.ndarray,
        images: np.ndarray,
        counts: np.ndarray,
        first: int,
    ) -> None:
        image = self.images
        n = self._images_with.view()
        if len(owner):
            # n_i -> n_i + 1 for the image's existing words: A_d of the images holding them follows.
            step = np.log1p(1.0 / n[existing])
            self._log_mass.view()[:] += np.bincount(images, weights=counts * step[owner], minlength=image)
        words, word_counts = np.unique(ids, return_counts=True)
        n[words] += 1
        self._first_word.extend(np.array([first], dtype=np.int64))
        self._mass.extend(np.array([float(word_counts.sum())]))
        self._log_mass.extend(np.array([float((word_counts * np.log(n[words])).sum())]))
        self._postings.add(words.astype(np.int32), image, word_counts.astype(np.int32), self._alive.view())

    def _purge(self) -> None:
        """Delete the words founded ``purge_after`` images ago that too few images have seen."""
        founder = self.images - 1 - self.config.purge_after
        if founder < 0 or self.config.min_images <= 1:
            return
        first_words = self._first_word.view()
        end = first_words[founder + 1] if founder + 1 < len(first_words) else len(self._words)
        founded = np.arange(first_words[founder], end)
        n = self._images_with.view()
        doomed = founded[self._alive.view()[founded] & (n[founded] < self.config.min_images)]
        if len(doomed) == 0:
            return
        owner, images, counts = self._postings.gather(doomed)
        self._mass.view()[:] -= np.bincount(images, weights=counts, minlength=self.images)
        self._log_mass.view()[:] -= np.bincount(
            images, weights=counts * np.log(n[doomed][owner]), minlength=self.images
        )
        self._alive.view()[doomed] = False

    # -- pickling ---------------------------------------------------------------------------------

    def __getstate__(self) -> dict[str, Any]:
        """Everything but the hash runs, which ``__setstate__`` rebuilds from the words."""
        state = dict(self.__dict__)
        del state["_index"]
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._index = _HashIndex(self.config)
        alive = self._alive.view()
        live = np.flatnonzero(alive)
        self._index.insert(self._words.view()[live], live, alive)


def _checked(descriptors: np.ndarray) -> np.ndarray:
    d = np.ascontiguousarray(descriptors, dtype=np.uint8)
    if d.ndim != 2 or d.shape[1] != DESCRIPTOR_BYTES:
        if d.size == 0:
            return np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
        raise ValueError(f"descriptors must be (N, {DESCRIPTOR_BYTES}) uint8, got {d.shape}")
    return d
