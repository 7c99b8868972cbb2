"""A DBoW2-style vocabulary tree for binary (ORB) descriptors, in numpy.

Training (Gálvez-López & Tardós, DBoW2): hierarchical k-majority clustering, i.e. k-medians in
Hamming space. Each node's descriptors are seeded with k-means++ (Hamming distance, squared, as
DBoW2), then assigned to the nearest centre and re-centred by a per-bit majority vote
(``np.unpackbits``; a tie gives 0) until the assignment stops changing or ``iterations`` runs out.
A node with at most ``k`` distinct descriptors gets one child per distinct descriptor; a node with
one gets a single copy of itself as child. That padding puts every leaf at depth ``levels``, so each
level is one flat array of nodes and ``words_at_level`` is a plain index at that level.

Weights: TF-IDF. IDF ``ln(N / n_i)`` over the N training images, ``n_i`` the images with a
descriptor quantised to word i (DBoW2 counts them by transforming the training images after
clustering); a word no training image reaches gets weight 0, as in DBoW2. TF is the word's share
of the image's descriptors. BoW vectors are L1-normalised and compared with DBoW2's L1 score
``s(v1, v2) = 1 - 0.5 |v1/|v1| - v2/|v2||_1``; for non-negative normalised vectors that equals
``sum_i min(v1_i, v2_i)`` over the shared words, which is what the inverted index sums.

Transforming descends all descriptors together, one level at a time: per descriptor, the Hamming
distances to (at most k) children of its current node, from ``np.bitwise_count`` on XORed uint64
words. The database's inverted index is a log-structured set of word-sorted posting blocks
(blocks of equal image count are merged, as in an LSM tree), so adding is amortised
O(log n) per posting and one query costs a few ``searchsorted`` calls per block.

Files: ``.npz`` with ``format``, ``version``, ``k``, ``levels``, per level ``centroids_<l>``
(uint8 (M_l, 32)) and ``parents_<l>`` (index into level l-1, non-decreasing), and ``idf``.
"""

from __future__ import annotations

import hashlib
import io
import time
import zipfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from frontends.errors import InputFileError

FILE_FORMAT = "symbiolcd2-orb-vocabulary"
FILE_VERSION = 1
DESCRIPTOR_BYTES = 32
#: Rows per chunk of a distance computation (bounds the (rows, k, 4) uint64 temporary).
_CHUNK = 1 << 15
#: Larger than any Hamming distance of 256-bit descriptors.
_FAR = 1 << 16


def hamming(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(len(a), len(b)) Hamming distances between two sets of 32-byte binary descriptors."""
    a64, b64 = _as_u64(a), _as_u64(b)
    out = np.empty((len(a64), len(b64)), dtype=np.int32)
    for start in range(0, len(a64), _CHUNK):
        block = a64[start : start + _CHUNK, None, :] ^ b64[None, :, :]
        out[start : start + _CHUNK] = np.bitwise_count(block).sum(axis=2, dtype=np.int32)
    return out


def _as_u64(descriptors: np.ndarray) -> np.ndarray:
    d = np.ascontiguousarray(descriptors, dtype=np.uint8)
    if d.ndim != 2 or d.shape[1] != DESCRIPTOR_BYTES:
        raise ValueError(f"descriptors must be (N, {DESCRIPTOR_BYTES}) uint8, got {d.shape}")
    return d.view(np.uint64)


@dataclass(frozen=True)
class BowVector:
    """A sparse, L1-normalised TF-IDF bag-of-words vector: sorted unique ``words`` and their ``weights``."""

    words: np.ndarray
    weights: np.ndarray

    def __len__(self) -> int:
        return len(self.words)


def empty_bow() -> BowVector:
    return BowVector(np.zeros(0, np.int64), np.zeros(0, np.float64))


def l1_score(a: BowVector, b: BowVector) -> float:
    """DBoW2's L1 score of two normalised BoW vectors: 1 for equal vectors, 0 without shared words."""
    _, ia, ib = np.intersect1d(a.words, b.words, assume_unique=True, return_indices=True)
    return float(np.minimum(a.weights[ia], b.weights[ib]).sum())


@dataclass(frozen=True)
class TrainingStats:
    images: int
    descriptors: int
    words: int
    seconds: float


class Vocabulary:
    """A vocabulary tree of branching ``k`` and depth ``levels`` with leaf IDF weights."""

    def __init__(
        self, k: int, centroids: Sequence[np.ndarray], parents: Sequence[np.ndarray], idf: np.ndarray
    ):
        if k < 2 or not centroids or len(centroids) != len(parents):
            raise ValueError("a vocabulary needs k >= 2 and one (centroids, parents) pair per level")
        self.k = k
        self.levels = len(centroids)
        self.centroids = [np.ascontiguousarray(c, dtype=np.uint8) for c in centroids]
        self.parents = [np.asarray(p, dtype=np.int64) for p in parents]
        self.idf = np.asarray(idf, dtype=np.float64)
        #: The file it was loaded from and that file's SHA-256 (None when built in memory).
        self.source: tuple[Path, str] | None = None
        # Per level, a (parents, k) table of child indices; missing children point at a far sentinel
        # row appended to the level's centroids (distance _FAR via the mask).
        self._children: list[np.ndarray] = []
        self._valid: list[np.ndarray] = []
        self._centroids64: list[np.ndarray] = []
        n_parents = 1
        for level in range(self.levels):
            parent = self.parents[level]
            counts = np.bincount(parent, minlength=n_parents)
            starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
            slot = np.arange(k)
            valid = slot[None, :] < counts[:, None]
            table = np.where(valid, starts[:, None] + slot[None, :], 0)
            self._children.append(table)
            self._valid.append(valid)
            self._centroids64.append(self.centroids[level].view(np.uint64))
            n_parents = len(parent)

    @property
    def size(self) -> int:
        """The number of words (leaves)."""
        return len(self.centroids[-1])

    def words_per_level(self) -> list[int]:
        return [len(c) for c in self.centroids]

    # -- quantisation -------------------------------------------------------------------------------

    def paths(self, descriptors: np.ndarray, depth: int | None = None) -> np.ndarray:
        """(N, depth) node index of each descriptor at levels 1..depth (column l-1 = level l; default L)."""
        d64 = _as_u64(descriptors)
        depth = self.levels if depth is None else depth
        path = np.zeros((len(d64), depth), dtype=np.int64)
        node = np.zeros(len(d64), dtype=np.int64)
        for level in range(depth):
            for start in range(0, len(d64), _CHUNK):
                part = slice(start, start + _CHUNK)
                children = self._children[level][node[part]]
                candidates = self._centroids64[level][children]
                distance = np.bitwise_count(candidates ^ d64[part, None, :]).sum(axis=2, dtype=np.int32)
                distance[~self._valid[level][node[part]]] = _FAR
                path[part, level] = children[np.arange(len(children)), distance.argmin(axis=1)]
            node = path[:, level]
        return path

    def words_at_level(self, descriptors: np.ndarray, level: int) -> np.ndarray:
        """Word id (node index within ``level``, 1 = coarsest, ``levels`` = leaves) of each descriptor."""
        if not 1 <= level <= self.levels:
            raise ValueError(f"level must be in 1..{self.levels}, got {level}")
        return self.paths(descriptors, level)[:, level - 1]

    def transform(self, descriptors: np.ndarray) -> BowVector:
        """The normalised TF-IDF BoW vector of one image's descriptors (empty for no descriptors)."""
        if len(descriptors) == 0:
            return empty_bow()
        return self._bow(self.paths(descriptors)[:, -1])

    def _bow(self, leaves: np.ndarray) -> BowVector:
        words, counts = np.unique(leaves, return_counts=True)
        weights = counts / len(leaves) * self.idf[words]
        keep = weights > 0
        words, weights = words[keep], weights[keep]
        total = weights.sum()
        if total <= 0:
            return empty_bow()
        return BowVector(words.astype(np.int64), weights / total)

    # -- training ----------------------------------------------------------------------------------

    @classmethod
    def train(
        cls,
        images: Sequence[np.ndarray],
        k: int = 10,
        levels: int = 5,
        seed: int = 0,
        max_descriptors: int | None = None,
        iterations: int = 10,
    ) -> tuple[Vocabulary, TrainingStats]:
        """Cluster the descriptors of ``images`` (one (N_i, 32) array each) and set IDF from the images.

        ``max_descriptors`` caps the clustered set by a seeded uniform sample; IDF always uses every image.
        """
        if k < 2 or levels < 1:
            raise ValueError("k must be >= 2 and levels >= 1")
        start = time.perf_counter()
        rng = np.random.default_rng(seed)
        per_image = [np.ascontiguousarray(d, dtype=np.uint8).reshape(-1, DESCRIPTOR_BYTES) for d in images]
        data = np.concatenate(per_image) if per_image else np.zeros((0, DESCRIPTOR_BYTES), np.uint8)
        if len(data) == 0:
            raise ValueError("no descriptors to train a vocabulary on")
        if max_descriptors is not None and len(data) > max_descriptors:
            data = data[np.sort(rng.choice(len(data), size=max_descriptors, replace=False))]
        centroids, parents = _cluster_tree(data, k, levels, rng, iterations)
        vocabulary = cls(k, centroids, parents, np.ones(len(centroids[-1])))
        vocabulary.idf = vocabulary._idf(per_image)
        stats = TrainingStats(len(per_image), len(data), vocabulary.size, time.perf_counter() - start)
        return vocabulary, stats

    def _idf(self, per_image: Iterable[np.ndarray]) -> np.ndarray:
        seen = np.zeros(self.size, dtype=np.int64)
        n_images = 0
        for descriptors in per_image:
            n_images += 1
            if len(descriptors):
                seen[np.unique(self.paths(descriptors)[:, -1])] += 1
        idf = np.zeros(self.size, dtype=np.float64)
        used = seen > 0
        idf[used] = np.log(n_images / seen[used])
        return idf

    # -- files -------------------------------------------------------------------------------------

    def save(self, path: str | Path) -> None:
        arrays: dict[str, Any] = {
            "format": np.array(FILE_FORMAT),
            "version": np.array(FILE_VERSION),
            "k": np.array(self.k),
            "levels": np.array(self.levels),
            "idf": self.idf.astype(np.float32),
        }
        for level in range(self.levels):
            arrays[f"centroids_{level + 1}"] = self.centroids[level]
            arrays[f"parents_{level + 1}"] = self.parents[level].astype(np.int32)
        target = Path(path)
        target.parent.mkdir(parents=True, exist_ok=True)
        with target.open("wb") as handle:
            np.savez_compressed(handle, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> Vocabulary:
        """Read a vocabulary ``.npz``; any missing, corrupt or inconsistent file is an ``InputFileError``."""
        source = Path(path)
        try:
            content = source.read_bytes()
            with np.load(io.BytesIO(content), allow_pickle=False) as npz:
                arrays = {name: npz[name] for name in npz.files}
        except FileNotFoundError:
            raise InputFileError(source, "vocabulary file not found") from None
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
            raise InputFileError(source, f"not a readable vocabulary .npz ({exc})") from None
        vocabulary = cls._from_arrays(source, arrays)
        vocabulary.source = (source.resolve(), hashlib.sha256(content).hexdigest())
        return vocabulary

    def __reduce_ex__(self, protocol: Any) -> Any:
        """A vocabulary read from a file pickles as the file's path and SHA-256 (a run checkpoint
        would otherwise copy ~10 MB each time); unpickling reloads it and checks the hash."""
        if self.source is None:
            return super().__reduce_ex__(protocol)
        return _reload, self.source

    @classmethod
    def _from_arrays(cls, source: Path, arrays: dict[str, np.ndarray]) -> Vocabulary:
        def fail(message: str) -> InputFileError:
            return InputFileError(source, f"invalid vocabulary: {message}")

        if "format" not in arrays or str(arrays["format"]) != FILE_FORMAT:
            raise fail(f"no '{FILE_FORMAT}' format tag (not a vocabulary file?)")
        if int(arrays.get("version", -1)) != FILE_VERSION:
            raise fail(f"version {arrays.get('version')} is not the supported version {FILE_VERSION}")
        try:
            k, levels = int(arrays["k"]), int(arrays["levels"])
            centroids = [arrays[f"centroids_{level}"] for level in range(1, levels + 1)]
            parents = [arrays[f"parents_{level}"] for level in range(1, levels + 1)]
            idf = arrays["idf"]
        except KeyError as exc:
            raise fail(f"missing array {exc}") from None
        if k < 2 or levels < 1:
            raise fail(f"k={k}, levels={levels}")
        n_parents = 1
        for level, (c, p) in enumerate(zip(centroids, parents, strict=True), start=1):
            if c.dtype != np.uint8 or c.ndim != 2 or c.shape[1] != DESCRIPTOR_BYTES or len(c) == 0:
                raise fail(f"centroids_{level} must be non-empty (M, 32) uint8, got {c.dtype} {c.shape}")
            if p.shape != (len(c),) or not np.issubdtype(p.dtype, np.integer):
                raise fail(f"parents_{level} must be {len(c)} integers")
            counts = np.bincount(p, minlength=n_parents) if p.size and p.min() >= 0 else None
            if counts is None or len(counts) != n_parents or np.any(np.diff(p) < 0):
                raise fail(f"parents_{level} must be sorted indices into level {level - 1}")
            if counts.min() < 1 or counts.max() > k:
                raise fail(f"every node of level {level - 1} needs 1..{k} children")
            n_parents = len(c)
        if idf.shape != (n_parents,) or not np.all(np.isfinite(idf)) or np.any(idf < 0):
            raise fail(f"idf must be {n_parents} finite non-negative weights")
        return cls(k, centroids, parents, idf)


def _cluster_tree(
    data: np.ndarray, k: int, levels: int, rng: np.random.Generator, iterations: int
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Breadth-first hierarchical k-majority clustering; per level the centroids and parent indices."""
    centroids: list[np.ndarray] = []
    parents: list[np.ndarray] = []
    # The members of each node of the previous level, as index arrays into ``data``.
    members: list[np.ndarray] = [np.arange(len(data))]
    for _ in range(levels):
        level_centroids: list[np.ndarray] = []
        level_parents: list[int] = []
        next_members: list[np.ndarray] = []
        for parent, idx in enumerate(members):
            centres, labels = _k_majority(data[idx], k, rng, iterations)
            for child in range(len(centres)):
                level_centroids.append(centres[child])
                level_parents.append(parent)
                next_members.append(idx[labels == child])
        centroids.append(np.stack(level_centroids))
        parents.append(np.array(level_parents, dtype=np.int64))
        members = next_members
    return centroids, parents


def _k_majority(
    descriptors: np.ndarray, k: int, rng: np.random.Generator, iterations: int
) -> tuple[np.ndarray, np.ndarray]:
    """Cluster one node: ((c, 32) centres with c <= k, (n,) labels). Every centre has members."""
    distinct, inverse = np.unique(descriptors, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    if len(distinct) <= k:
        # DBoW2's trivial case: one cluster per (distinct) descriptor; a single one copies itself.
        return distinct, inverse
    centres = _kmeans_pp(descriptors, k, rng)
    bits = np.unpackbits(descriptors, axis=1)
    labels = np.full(len(descriptors), -1, dtype=np.int64)
    for _ in range(iterations):
        new_labels = hamming(descriptors, centres).argmin(axis=1)
        if np.array_equal(new_labels, labels):
            break
        labels = new_labels
        used = np.unique(labels)
        order = np.argsort(labels, kind="stable")
        starts = np.searchsorted(labels[order], used)
        ones = np.add.reduceat(bits[order], starts, axis=0, dtype=np.int32)
        counts = np.diff(np.append(starts, len(labels)))
        centres = np.packbits((2 * ones > counts[:, None]).astype(np.uint8), axis=1)
        # Empty clusters vanish; relabel so that the labels index the remaining centres.
        labels = np.searchsorted(used, labels)
    labels = hamming(descriptors, centres).argmin(axis=1)
    used = np.unique(labels)
    return centres[used], np.searchsorted(used, labels)


def _kmeans_pp(descriptors: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding with squared Hamming distances (as DBoW2's ``initiateClustersKMpp``)."""
    chosen = [int(rng.integers(len(descriptors)))]
    nearest = hamming(descriptors, descriptors[chosen[-1] : chosen[-1] + 1])[:, 0].astype(np.float64)
    while len(chosen) < k:
        weights = nearest**2
        total = weights.sum()
        if total <= 0:
            break
        pick = int(np.searchsorted(np.cumsum(weights), rng.random() * total, side="right"))
        pick = min(pick, len(descriptors) - 1)
        chosen.append(pick)
        distance = hamming(descriptors, descriptors[pick : pick + 1])[:, 0]
        nearest = np.minimum(nearest, distance)
    return descriptors[chosen].copy()


class BowDatabase:
    """An inverted index of BoW vectors: ``query`` scores one vector against every stored one at once."""

    def __init__(self) -> None:
        # Blocks of postings sorted by word: (words, entries, weights, image count); image counts are
        # powers of two, largest first.
        self._blocks: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []
        self._count = 0

    def __len__(self) -> int:
        return self._count

    def add(self, bow: BowVector) -> int:
        """Store ``bow``; returns its entry index (0, 1, 2, ... in insertion order)."""
        entry = self._count
        self._count += 1
        block = (bow.words, np.full(len(bow), entry, dtype=np.int64), bow.weights, 1)
        self._blocks.append(block)
        while len(self._blocks) >= 2 and self._blocks[-1][3] == self._blocks[-2][3]:
            right, left = self._blocks.pop(), self._blocks.pop()
            words = np.concatenate([left[0], right[0]])
            order = np.argsort(words, kind="stable")
            self._blocks.append(
                (
                    words[order],
                    np.concatenate([left[1], right[1]])[order],
                    np.concatenate([left[2], right[2]])[order],
                    left[3] + right[3],
                )
            )
        return entry

    def query(self, bow: BowVector) -> np.ndarray:
        """L1 scores of ``bow`` against every stored entry, as a (len(self),) array indexed by entry."""
        scores = np.zeros(self._count, dtype=np.float64)
        if len(bow) == 0:
            return scores
        for words, entries, weights, _ in self._blocks:
            lo = np.searchsorted(words, bow.words, side="left")
            hi = np.searchsorted(words, bow.words, side="right")
            lengths = hi - lo
            total = int(lengths.sum())
            if total == 0:
                continue
            # Concatenated ranges [lo_i, hi_i): positions = repeat(lo) + offset within each range.
            offsets = np.arange(total) - np.repeat(np.cumsum(lengths) - lengths, lengths)
            positions = np.repeat(lo, lengths) + offsets
            shared = np.minimum(weights[positions], np.repeat(bow.weights, lengths))
            scores += np.bincount(entries[positions], weights=shared, minlength=self._count)
        return scores


def _reload(path: Path, sha256: str) -> Vocabulary:
    """The pickled vocabulary: reloaded from its file, which must not have changed."""
    vocabulary = Vocabulary.load(path)
    if vocabulary.source is None or vocabulary.source[1] != sha256:
        raise InputFileError(path, "vocabulary file changed since it was pickled (e.g. in a run checkpoint)")
    return vocabulary
