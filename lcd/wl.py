"""Incremental exact Weisfeiler-Lehman subtree kernel with the vertex-histogram base kernel.

``k_WL(G, G') = sum_{t=0..h} <phi_t(G), phi_t(G')>`` (paper, section III-E; Shervashidze et al.
2011), ``phi_t`` the histogram of the WL labels after ``t`` relabellings, normalised as
``k(a, b) / sqrt(k(a, a) k(b, b))``. ``iterations`` = h counts relabellings: iterations 0..h, h + 1
histograms, iteration 0 being the input labels. That is the paper's h and grakel's ``n_iter``
(grakel's ``WeisfeilerLehman`` runs ``n_iter + 1`` base kernels); h = 0 is the plain vertex
histogram, which grakel's WL rejects (``GrakelWL`` then uses grakel's ``VertexHistogram``).
A graph without nodes has ``k(a, a) = 0`` and similarity 0 to every graph (grakel's 0/0 -> 0).

Exactness: two nodes of any two graphs get the same label at iteration t iff they have the same
label at t - 1 and the same multiset of neighbour labels at t - 1, as in grakel's dictionary; only
the label ids differ, so the kernel values are identical (raw values are integers, exact in float64).

Why not one dictionary entry per label: keyframe graphs are stars whose own WL partition stops
refining after 2-3 iterations, yet from there on almost every class gets a fresh label at every
iteration (they no longer match any other keyframe). At h = 50 that is ~45 labels per class per
keyframe, ~40k per keyframe, in the dictionary and in the feature matrix. Instead:

- Chains. Once a graph's partition is final (iteration ``s``), a class's later labels depend on the
  graph alone. So when an added graph's class gets a new label at iteration ``t0 >= s`` we allocate a
  chain of ids for iterations ``t0..h`` and record the class as its anchor. The dictionary holds only
  the chain's first label: the signature of position ``j + 1`` is implicitly (position ``j``, the
  anchor's neighbour multiset at iteration ``t0 + j``), checked on demand against the anchor graph's
  stored label trajectory ("continuation"). Labels created before ``s`` are chains of length 1.
  Label id = chain * (h + 1) + position.
- Runs. A node enters a chain only at its first position (any later position needs the previous one
  as its own previous label), so a class's labels over 0..h are runs ``(chain, length L)`` from the
  chain start, and ``<phi(G), phi(G')> = sum over shared chains of n n' min(L, L')``. A graph is
  stored as its runs (count per (chain, L)); one query is a few ``searchsorted`` calls and sparse
  products against an LSM-style list of posting blocks (blocks of equal graph count are merged).
- Early stop. From iteration ``s`` on, if every class either runs on its own new chain, is unknown
  (query), or continued a stored chain whose anchor's neighbours no longer change chain while all
  its own neighbours continued too, nothing changes any more (the neighbour multisets advance in
  lock step), so the remaining iterations are filled in without lookups.
Self-similarities come from the graph's own partitions: ``sum_t sum_classes size^2``.

IDF weighting (``idf_power`` p = 1 or 2; 0, the default, is the plain kernel above, unchanged):
``k(G, G') = sum_t sum_l w(l) phi_t(G)[l] phi_t(G')[l]`` with ``w(l) = idf(r)^p``, r the input
label (iteration 0) that label l descends from (a WL label determines its previous one, so every
label, and every chain, has one root), ``idf(r) = ln(N / df(r))`` over the stored graphs *and the
query* (N = stored + 1; df counts the query if it holds r), so a query's scores do not depend on
whether it is stored afterwards and no weight is infinite. p = 2 is the cosine of TF-IDF label
histograms. Scores always use the current IDF for the stored graphs too: each stored graph keeps
``Q(r) = sum_t sum_{classes of root r} size^2`` per root (root postings) and the sums
``S = sum_r Q``, ``A1 = sum_r Q ln df``, ``A2 = sum_r Q ln^2 df``, from which its self-similarity
under any N is ``S ln^2 N - 2 A1 ln N + A2`` (p = 2) or ``S ln N - A1`` (p = 1); the query's roots
change df by one for the graphs in their root postings (a correction read at scoring), and adding
a graph updates A1, A2 of those graphs. Both reads cost what a query's iteration-0 postings cost.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from lcd.graph import LabelledGraph

#: Shift separating the segment index from the label in combined sort keys (labels < 2**40).
_SEG_SHIFT = 40


class _Buffer:
    """An append-only numpy array with amortised O(1) appends."""

    def __init__(self, dtype: type, data: np.ndarray | None = None) -> None:
        initial: np.ndarray = np.zeros(0, dtype=dtype) if data is None else np.asarray(data, dtype=dtype)
        self._data: np.ndarray = np.zeros(max(16, 2 * len(initial)), dtype=dtype)
        self._data[: len(initial)] = initial
        self._size = len(initial)

    def __len__(self) -> int:
        return self._size

    def extend(self, values: np.ndarray) -> None:
        end = self._size + len(values)
        if end > len(self._data):
            grown = np.zeros(max(end, 2 * len(self._data)), dtype=self._data.dtype)
            grown[: self._size] = self._data[: self._size]
            self._data = grown
        self._data[self._size : end] = values
        self._size = end

    def view(self) -> np.ndarray:
        return self._data[: self._size]

    def __getstate__(self) -> dict[str, object]:
        """Pickles the used part only (half of the capacity is empty after a growth step)."""
        return {"data": self.view(), "capacity": len(self._data)}

    def __setstate__(self, state: dict[str, np.ndarray | int]) -> None:
        data = np.asarray(state["data"])
        self._data = np.zeros(int(state["capacity"]), dtype=data.dtype)
        self._data[: len(data)] = data
        self._size = len(data)


def _ranges(starts: np.ndarray, lengths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(segment of each element, index of each element) of the ranges ``starts[i] + 0..lengths[i]-1``."""
    total = int(lengths.sum())
    seg = np.repeat(np.arange(len(starts), dtype=np.int64), lengths)
    offsets = np.cumsum(lengths) - lengths
    return seg, np.repeat(starts - offsets, lengths) + np.arange(total, dtype=np.int64)


def _sort_segments(seg: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` (>= -1, < 2**40) sorted within each segment; ``seg`` must be non-decreasing."""
    keys = np.sort((seg << _SEG_SHIFT) | (values + 1))
    return (keys & ((1 << _SEG_SHIFT) - 1)) - 1


def _row_classes(rows: np.ndarray) -> tuple[np.ndarray, int]:
    """Class of each row (equal rows, equal class) of a non-negative int64 matrix, and the class count."""
    if len(rows) <= 1:
        return np.zeros(len(rows), dtype=np.int64), len(rows)
    radix = int(rows.max()) + 1
    if radix ** rows.shape[1] < 2**62:
        # Mixed-radix code: one 1-D unique instead of a row-wise (structured) one.
        code = np.zeros(len(rows), dtype=np.int64)
        for column in rows.T:
            code = code * radix + column
        unique, inverse = np.unique(code, return_inverse=True)
    else:
        unique, inverse = np.unique(rows, axis=0, return_inverse=True)
    return inverse.reshape(-1).astype(np.int64), len(unique)


@dataclass(frozen=True)
class _Refinement:
    """A graph's own WL partitions, independent of every other graph."""

    labels: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    #: Node -> class at iterations 0..s; the last one is final (or iteration h was reached).
    partitions: list[np.ndarray]
    #: A representative node per class, per partition.
    representatives: list[np.ndarray]
    self_similarity: float

    @property
    def stable(self) -> int:
        return len(self.partitions) - 1


def _adjacency(graph: LabelledGraph) -> tuple[np.ndarray, np.ndarray]:
    """CSR adjacency; duplicate edges collapse, a self-loop makes a node its own neighbour once (grakel)."""
    n = graph.num_nodes
    edges = np.asarray(graph.edges, dtype=np.int64).reshape(-1, 2)
    if edges.size and (edges.min() < 0 or edges.max() >= n):
        raise ValueError(f"edge endpoints must be in 0..{n - 1}")
    low, high = edges.min(axis=1), edges.max(axis=1)
    pairs = np.unique(low * max(n, 1) + high)
    low, high = pairs // max(n, 1), pairs % max(n, 1)
    loop = low == high
    src = np.concatenate([low[~loop], high[~loop], low[loop]])
    dst = np.concatenate([high[~loop], low[~loop], low[loop]])
    order = np.lexsort((dst, src))
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(src, minlength=n), out=indptr[1:])
    return indptr, dst[order]


def _refine(graph: LabelledGraph, iterations: int) -> _Refinement:
    labels = np.asarray(graph.labels, dtype=np.int64).reshape(-1)
    indptr, indices = _adjacency(graph)
    degree = np.diff(indptr)
    # Nodes grouped by degree, each group's neighbours as an (nodes, degree) matrix.
    groups = []
    for d in np.unique(degree).tolist():
        nodes = np.flatnonzero(degree == d)
        groups.append((nodes, indices[indptr[nodes][:, None] + np.arange(d)]))
    cls = np.unique(labels, return_inverse=True)[1].reshape(-1).astype(np.int64)
    partitions = [cls]
    count = int(cls.max()) + 1 if len(cls) else 0
    for _ in range(iterations):
        refined = np.empty_like(cls)
        next_count = 0
        for nodes, neighbours in groups:
            rows = np.column_stack([cls[nodes], np.sort(cls[neighbours], axis=1)])
            inverse, k = _row_classes(rows)
            refined[nodes] = inverse + next_count
            next_count += k
        if next_count == count:
            break
        partitions.append(refined)
        cls, count = refined, next_count
    sizes = [float(np.square(np.bincount(p)).sum()) if len(p) else 0.0 for p in partitions]
    self_similarity = sum(sizes) + (iterations + 1 - len(partitions)) * sizes[-1]
    representatives = [np.unique(p, return_index=True)[1].astype(np.int64) for p in partitions]
    return _Refinement(labels, indptr, indices, partitions, representatives, self_similarity)


def _root_mass(ref: _Refinement, iterations: int) -> np.ndarray:
    """``Q(r) = sum_t sum_{classes of root r} size^2`` per input label r (class of partition 0)."""
    root = ref.partitions[0]
    mass = np.zeros(len(ref.representatives[0]), dtype=np.float64)
    last = len(ref.partitions) - 1
    for t, (partition, reps) in enumerate(zip(ref.partitions, ref.representatives, strict=True)):
        times = 1 if t < last else iterations + 1 - last
        squares = np.square(np.bincount(partition)).astype(np.float64)
        mass += times * np.bincount(root[reps], weights=squares, minlength=len(mass))
    return mass


def _idf_weight(log_n: float, df: np.ndarray, power: int) -> np.ndarray:
    """``ln(N / df)^power`` (df >= 1)."""
    return (log_n - np.log(df.astype(np.float64))) ** power


def _capacity(sizes: np.ndarray) -> np.ndarray:
    """The smallest power of two >= each size (0 for 0)."""
    exponent = np.frexp(np.maximum(sizes - 1, 0).astype(np.float64))[1]
    return np.where(sizes > 0, np.left_shift(1, exponent.astype(np.int64)), 0)


class _Postings:
    """Every stored graph's runs, listed per chain as (graph, run length, count).

    A chain's list lies contiguously in one arena with a power-of-two capacity (derived from its
    size); a list that outgrows it moves to the arena's end. Appends are amortised O(1), scoring
    reads a chain's list at a known offset (no search), and the abandoned space is below the live
    capacity (a geometric series per chain)."""

    def __init__(self) -> None:
        self.start = _Buffer(np.int64)
        self.size = _Buffer(np.int64)
        # Graph rows, run lengths and counts stay far below 2**31; int32 halves the largest part of
        # the database (docs/2026-12-06-long-runs.md).
        self.graph = _Buffer(np.int32)
        self.run = _Buffer(np.int32)
        self.count = _Buffer(np.int32)

    def add_chains(self, count: int) -> None:
        self.start.extend(np.zeros(count, dtype=np.int64))
        self.size.extend(np.zeros(count, dtype=np.int64))

    def append(self, chains: np.ndarray, graphs: np.ndarray, runs: np.ndarray, counts: np.ndarray) -> None:
        """Append postings; ``chains`` must be non-decreasing."""
        if len(chains) == 0:
            return
        unique, first, added = np.unique(chains, return_index=True, return_counts=True)
        start, size = self.start.view(), self.size.view()
        begin, used = start[unique], size[unique]
        grow = used + added > _capacity(used)
        if grow.any():
            capacity = _capacity(used[grow] + added[grow])
            moved = len(self.graph) + np.cumsum(capacity) - capacity
            _, source = _ranges(begin[grow], used[grow])
            _, target = _ranges(moved, used[grow])
            for arena in (self.graph, self.run, self.count):
                arena.extend(np.zeros(int(capacity.sum()), dtype=np.int32))
                data = arena.view()
                data[target] = data[source]
            begin[grow] = moved
            start[unique] = begin
        rank = np.arange(len(chains)) - np.repeat(first, added)
        position = np.repeat(begin + used, added) + rank
        self.graph.view()[position] = graphs
        self.run.view()[position] = runs
        self.count.view()[position] = counts
        size[unique] = used + added

    def listed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(chain, graph, run length, count) of every posting, by chain."""
        size = self.size.view()
        chain, position = _ranges(self.start.view(), size)
        return chain, self.graph.view()[position], self.run.view()[position], self.count.view()[position]

    def __getstate__(self) -> dict[str, np.ndarray]:
        """Pickles the live postings only (the arenas' abandoned and spare space is most of them)."""
        _, graph, run, count = self.listed()
        return {"size": self.size.view(), "graph": graph, "run": run, "count": count}

    def __setstate__(self, state: dict[str, np.ndarray]) -> None:
        """Each chain's list at its own offset with its capacity (a function of its size, as
        ``append`` assumes): what is read, and every later append, are as before pickling."""
        size = np.asarray(state["size"], dtype=np.int64)
        capacity = _capacity(size)
        start = np.cumsum(capacity) - capacity
        _, position = _ranges(start, size)
        self.start, self.size = _Buffer(np.int64, start), _Buffer(np.int64, size)
        arenas = []
        for name in ("graph", "run", "count"):
            arena = np.zeros(int(capacity.sum()), dtype=np.int32)
            arena[position] = state[name]
            arenas.append(_Buffer(np.int32, arena))
        self.graph, self.run, self.count = arenas


@dataclass(frozen=True)
class _Relabelled:
    """A graph's runs (by chain), and for an added graph the trajectory data to store."""

    chains: np.ndarray
    runs: np.ndarray
    counts: np.ndarray
    self_similarity: float
    trajectory_keys: np.ndarray
    trajectory_bases: np.ndarray
    adjacency_lengths: np.ndarray
    adjacency: np.ndarray
    ready: np.ndarray
    #: IDF mode: root chain of each input label of the graph (-1: unknown), and its ``Q(r)``.
    roots: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    root_mass: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.float64))


class WLKernel:
    """Exact incremental WL subtree kernel (see the module docstring); h = ``iterations``."""

    def __init__(self, iterations: int, idf_power: int = 0) -> None:
        if iterations < 0:
            raise ValueError(f"iterations must be >= 0, got {iterations}")
        if idf_power not in (0, 1, 2):
            raise ValueError(f"idf_power must be 0, 1 or 2, got {idf_power}")
        self.iterations = iterations
        #: 0 = the plain kernel; 1 / 2 = labels weighted by idf / idf^2 of their root (docstring).
        self.idf_power = idf_power
        self._width = iterations + 1
        #: Input label -> label id (iteration 0).
        self._initial: dict[int, int] = {}
        #: Signature bytes (previous label, sorted neighbour labels; int64) -> label id (a chain start).
        self._signatures: dict[bytes, int] = {}
        self._chain_length = _Buffer(np.int64)
        #: Anchor class (global class id) of a chain, -1 for a length-1 chain.
        self._chain_anchor = _Buffer(np.int64)
        # Per global class (the final classes of every stored graph, in add order): its label
        # trajectory from the graph's stable iteration (segments keyed class * (h + 1) + start),
        # its neighbour classes with multiplicity, and the iteration after which all of them
        # stay on their chains.
        self._trajectory_keys = _Buffer(np.int64)
        self._trajectory_bases = _Buffer(np.int64)
        self._adjacency_ptr = _Buffer(np.int64, np.zeros(1))
        self._adjacency = _Buffer(np.int64)
        self._ready = _Buffer(np.int64)
        self._self_similarity = _Buffer(np.float64)
        self._postings = _Postings()
        # IDF mode only: per chain its root chain (an iteration-0 label's chain) and, for roots,
        # df (stored graphs holding the root) and the postings (graph, Q); per graph S, A1, A2.
        self._chain_root = _Buffer(np.int64)
        self._df = _Buffer(np.int64)
        self._root_postings = _Postings()
        self._mass = _Buffer(np.float64)
        self._log_mass = _Buffer(np.float64)
        self._log2_mass = _Buffer(np.float64)
        #: The last scoring's root postings, (roots array, gathered), for the store that follows.
        self._gathered: tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None

    def __len__(self) -> int:
        return len(self._self_similarity)

    def add(self, graph: LabelledGraph) -> int:
        """Store ``graph``; returns its row (add order)."""
        self._store(self._relabel(graph, add=True))
        return len(self) - 1

    def query(self, graph: LabelledGraph) -> np.ndarray:
        """Normalised kernel values of ``graph`` against every stored graph; changes nothing."""
        return self._scores(self._relabel(graph, add=False))

    def add_and_query(self, graph: LabelledGraph) -> np.ndarray:
        """Scores against the graphs stored before it (as ``query``), then stores it."""
        relabelled = self._relabel(graph, add=True)
        scores = self._scores(relabelled)
        self._store(relabelled)
        return scores

    # -- relabelling ---------------------------------------------------------------------------

    def _relabel(self, graph: LabelledGraph, add: bool) -> _Relabelled:
        h = self.iterations
        ref = _refine(graph, h)
        s = ref.stable
        final, final_reps = ref.partitions[-1], ref.representatives[-1]
        k = len(final_reps)
        offset = len(self._ready)
        columns_labels = np.full((k, self._width), -1, dtype=np.int64)
        columns_starts = np.zeros((k, self._width), dtype=bool)

        reps = ref.representatives[0]
        labels = np.full(len(reps), -1, dtype=np.int64)
        found = list(map(self._initial.get, ref.labels[reps].tolist()))
        hit = np.array([f is not None for f in found], dtype=bool)
        labels[hit] = [f for f in found if f is not None]
        if add and not hit.all():
            missing = np.flatnonzero(~hit)
            labels[missing] = self._create(missing, 0, s, offset, None)
            self._initial.update(
                zip(ref.labels[reps[missing]].tolist(), labels[missing].tolist(), strict=True)
            )
        starts = np.ones(len(reps), dtype=bool)
        roots = np.where(labels >= 0, labels // self._width, -1)
        self._record(columns_labels, columns_starts, ref, 0, labels, starts)
        # Neighbour units of the final classes, fixed from iteration s on.
        final_seg, final_nodes = _ranges(ref.indptr[final_reps], np.diff(ref.indptr)[final_reps])
        final_neighbour_units = final[ref.indices[final_nodes]]
        for t in range(1, h + 1):
            previous_partition = ref.partitions[min(t - 1, s)]
            reps = ref.representatives[min(t, s)]
            if t > s:
                seg, neighbour_units, parent = final_seg, final_neighbour_units, np.arange(k)
            else:
                seg, nodes = _ranges(ref.indptr[reps], np.diff(ref.indptr)[reps])
                neighbour_units, parent = previous_partition[ref.indices[nodes]], previous_partition[reps]
            prev = labels[parent]
            neighbour_labels = _sort_segments(seg, labels[neighbour_units])
            degree = np.diff(ref.indptr)[reps]
            labels, starts = self._step(t, s, offset, add, prev, seg, neighbour_labels, degree)
            self._record(columns_labels, columns_starts, ref, t, labels, starts)
            if t >= s and self._settled(t, offset, add, labels, starts, final_seg, final_neighbour_units):
                alive = labels >= 0
                steps = np.arange(1, h - t + 1, dtype=np.int64)
                columns_labels[:, t + 1 :] = np.where(alive[:, None], labels[:, None] + steps, -1)
                break
        runs = self._runs(columns_labels, columns_starts, np.bincount(final, minlength=k))
        if not add:
            empty = np.zeros(0, dtype=np.int64)
            relabelled = _Relabelled(*runs, ref.self_similarity, empty, empty, empty, empty, empty)
        else:
            relabelled = self._trajectory(
                ref, columns_labels, columns_starts, final_seg, final_neighbour_units, runs, offset
            )
        if self.idf_power:
            relabelled = replace(relabelled, roots=roots, root_mass=_root_mass(ref, h))
        return relabelled

    def _create(self, units: np.ndarray, t: int, s: int, offset: int, roots: np.ndarray | None) -> np.ndarray:
        """New chain-start labels of ``units`` at iteration t: chains to h anchored at the unit's global
        class once the partition is final (t >= s), else single labels. ``roots``: the new chains' root
        chains (None: they are roots, at t = 0)."""
        first = len(self._chain_length)
        if self.idf_power:
            own = np.arange(first, first + len(units), dtype=np.int64)
            self._chain_root.extend(own if roots is None else roots)
            self._df.extend(np.zeros(len(units), dtype=np.int64))
            self._root_postings.add_chains(len(units))
        final = t >= s
        self._chain_length.extend(
            np.full(len(units), self.iterations - t + 1 if final else 1, dtype=np.int64)
        )
        self._postings.add_chains(len(units))
        self._chain_anchor.extend(units + offset if final else np.full(len(units), -1, dtype=np.int64))
        return np.arange(first, first + len(units), dtype=np.int64) * self._width

    def _record(
        self,
        columns_labels: np.ndarray,
        columns_starts: np.ndarray,
        ref: _Refinement,
        t: int,
        labels: np.ndarray,
        starts: np.ndarray,
    ) -> None:
        """Store iteration t's unit labels per final class (unit of its representative)."""
        units = ref.partitions[min(t, ref.stable)][ref.representatives[-1]]
        columns_labels[:, t] = labels[units]
        columns_starts[:, t] = starts[units]

    def _step(
        self,
        t: int,
        s: int,
        offset: int,
        add: bool,
        prev: np.ndarray,
        seg: np.ndarray,
        neighbour_labels: np.ndarray,
        degree: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Labels at iteration t of units with previous labels ``prev`` and sorted neighbour labels."""
        width = self._width
        n = len(prev)
        labels = np.full(n, -1, dtype=np.int64)
        starts = np.zeros(n, dtype=bool)
        alive = prev >= 0
        chain = np.where(alive, prev // width, 0)
        position = prev - chain * width
        anchor = self._chain_anchor.view()[chain] if len(self._chain_anchor) else np.zeros(n, np.int64)
        length = self._chain_length.view()[chain] if len(self._chain_length) else np.zeros(n, np.int64)
        own = alive & (anchor >= offset) if add else np.zeros(n, dtype=bool)
        labels[own] = prev[own] + 1
        work = alive & ~own
        if not add:
            # A neighbour without a stored label: the signature cannot be stored anywhere.
            work &= np.bincount(seg[neighbour_labels < 0], minlength=n) == 0
        candidate = np.flatnonzero(work & (anchor >= 0) & (position + 1 < length))
        offsets = np.cumsum(degree) - degree
        passed = self._continues(candidate, anchor[candidate], t - 1, offsets, degree, neighbour_labels)
        labels[passed] = prev[passed] + 1
        work[passed] = False
        rest = np.flatnonzero(work)
        if rest.size:
            keys = self._signature_keys(rest, prev, offsets, degree, neighbour_labels)
            found = list(map(self._signatures.get, keys))
            hit = np.array([f is not None for f in found], dtype=bool)
            labels[rest[hit]] = [f for f in found if f is not None]
            starts[rest[hit]] = True
            if add and not hit.all():
                missing = rest[~hit]
                roots = self._chain_root.view()[prev[missing] // width] if self.idf_power else None
                labels[missing] = self._create(missing, t, s, offset, roots)
                starts[missing] = True
                new_keys = [key for key, h in zip(keys, hit.tolist(), strict=True) if not h]
                self._signatures.update(zip(new_keys, labels[missing].tolist(), strict=True))
        return labels, starts

    def _signature_keys(
        self,
        units: np.ndarray,
        prev: np.ndarray,
        offsets: np.ndarray,
        degree: np.ndarray,
        neighbour_labels: np.ndarray,
    ) -> list[bytes]:
        """(previous label, sorted neighbour labels) of ``units`` as int64 bytes, the dictionary key."""
        sizes = degree[units] + 1
        begin = np.cumsum(sizes) - sizes
        flat = np.empty(int(sizes.sum()), dtype=np.int64)
        flat[begin] = prev[units]
        flat[_ranges(begin + 1, degree[units])[1]] = neighbour_labels[
            _ranges(offsets[units], degree[units])[1]
        ]
        buffer = flat.tobytes()
        return [buffer[8 * b : 8 * (b + z)] for b, z in zip(begin.tolist(), sizes.tolist(), strict=True)]

    def _labels_at(self, classes: np.ndarray, t: int) -> np.ndarray:
        """Labels at iteration t of stored global classes (t >= their graph's stable iteration)."""
        keys = self._trajectory_keys.view()
        index = np.searchsorted(keys, classes * self._width + t, side="right") - 1
        return self._trajectory_bases.view()[index] + (t - keys[index] % self._width)

    def _continues(
        self,
        units: np.ndarray,
        anchors: np.ndarray,
        t: int,
        offsets: np.ndarray,
        degree: np.ndarray,
        neighbour_labels: np.ndarray,
    ) -> np.ndarray:
        """The ``units`` whose neighbour multiset at iteration t equals their chain anchor's."""
        ptr = self._adjacency_ptr.view()
        anchor_degree = ptr[anchors + 1] - ptr[anchors]
        same = degree[units] == anchor_degree
        units, anchors, anchor_degree = units[same], anchors[same], anchor_degree[same]
        if units.size == 0:
            return units
        seg, index = _ranges(offsets[units], degree[units])
        ours = neighbour_labels[index]
        anchor_seg, anchor_index = _ranges(ptr[anchors], anchor_degree)
        theirs = _sort_segments(anchor_seg, self._labels_at(self._adjacency.view()[anchor_index], t))
        mismatches = np.bincount(seg[ours != theirs], minlength=len(units))
        return units[mismatches == 0]

    def _settled(
        self,
        t: int,
        offset: int,
        add: bool,
        labels: np.ndarray,
        starts: np.ndarray,
        seg: np.ndarray,
        neighbour_units: np.ndarray,
    ) -> bool:
        """Whether the labels from iteration t on just advance along their chains (module docstring);
        t >= s, so the units are the final classes and ``neighbour_units`` their neighbours' classes."""
        if starts.any():
            return False
        alive = labels >= 0
        chain = labels[alive] // self._width
        anchors = self._chain_anchor.view()[chain]
        followed = anchors < offset if add else np.ones(len(chain), dtype=bool)
        if not followed.any():
            return True
        follower = np.zeros(len(labels), dtype=bool)
        follower[np.flatnonzero(alive)[followed]] = True
        if not follower[neighbour_units[follower[seg]]].all():
            return False
        return bool((self._ready.view()[anchors[followed]] <= t - 1).all())

    def _runs(
        self, labels: np.ndarray, starts: np.ndarray, sizes: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(chain, run length, count) of the class label rows, by chain."""
        alive = labels >= 0
        flat_starts = starts[alive]
        run = np.cumsum(flat_starts) - 1
        lengths = np.bincount(run) if len(run) else np.zeros(0, dtype=np.int64)
        chains = labels[alive][flat_starts] // self._width
        counts = np.repeat(sizes, alive.sum(axis=1))[flat_starts]
        radix = self._width + 1
        keys, inverse = np.unique(chains * radix + lengths, return_inverse=True)
        return keys // radix, keys % radix, np.bincount(inverse.reshape(-1), weights=counts).astype(np.int64)

    def _trajectory(
        self,
        ref: _Refinement,
        labels: np.ndarray,
        starts: np.ndarray,
        seg: np.ndarray,
        neighbour_units: np.ndarray,
        runs: tuple[np.ndarray, np.ndarray, np.ndarray],
        offset: int,
    ) -> _Relabelled:
        s, width = ref.stable, self._width
        k = len(labels)
        # Segments from iteration s: always one at s, then one per chain start.
        begins = starts[:, s:].copy()
        begins[:, 0] = True
        cls, when = np.nonzero(begins)
        trajectory_keys = (cls + offset) * width + when + s
        trajectory_bases = labels[cls, when + s]
        settle = np.zeros(k, dtype=np.int64)
        np.maximum.at(settle, cls, when + s)
        degree = np.bincount(seg, minlength=k)
        ready = np.full(k, -1, dtype=np.int64)
        if len(seg):
            np.maximum.at(ready, seg, settle[neighbour_units])
        return _Relabelled(
            *runs,
            ref.self_similarity,
            trajectory_keys,
            trajectory_bases,
            degree,
            neighbour_units + offset,
            ready,
        )

    # -- storage and scoring -------------------------------------------------------------------

    def _store(self, r: _Relabelled) -> None:
        row = len(self)
        self._trajectory_keys.extend(r.trajectory_keys)
        self._trajectory_bases.extend(r.trajectory_bases)
        self._adjacency_ptr.extend(self._adjacency_ptr.view()[-1] + np.cumsum(r.adjacency_lengths))
        self._adjacency.extend(r.adjacency)
        self._ready.extend(r.ready)
        self._self_similarity.extend(np.array([r.self_similarity]))
        self._postings.append(r.chains, np.full(len(r.chains), row, dtype=np.int64), r.runs, r.counts)
        if self.idf_power:
            self._store_roots(r.roots, r.root_mass, row)

    def _gather_roots(self, roots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(index into ``roots``, graph, Q) of the root postings of ``roots`` (>= 0)."""
        postings = self._root_postings
        owner, position = _ranges(postings.start.view()[roots], postings.size.view()[roots])
        return owner, postings.graph.view()[position], postings.count.view()[position].astype(np.float64)

    def _store_roots(self, roots: np.ndarray, mass: np.ndarray, row: int) -> None:
        """df of the graph's roots grows by one: A1, A2 of the graphs holding them follow."""
        df = self._df.view()
        old = df[roots].astype(np.float64)
        cached, self._gathered = self._gathered, None
        # add_and_query: the scoring read these postings already (nothing was appended since).
        owner, graphs, q = (
            cached[1] if cached is not None and cached[0] is roots else self._gather_roots(roots)
        )
        if len(graphs):
            # A root new to the store (df 0) has no postings: its log is never read.
            log_old, log_new = np.log(np.maximum(old, 1.0)), np.log(old + 1.0)
            self._log_mass.view()[:] += np.bincount(graphs, q * (log_new - log_old)[owner], minlength=row)
            self._log2_mass.view()[:] += np.bincount(
                graphs, q * (log_new**2 - log_old**2)[owner], minlength=row
            )
        df[roots] += 1
        log_df = np.log(old + 1.0)
        self._mass.extend(np.array([mass.sum()]))
        self._log_mass.extend(np.array([(mass * log_df).sum()]))
        self._log2_mass.extend(np.array([(mass * log_df**2).sum()]))
        order = np.argsort(roots, kind="stable")
        self._root_postings.append(
            roots[order],
            np.full(len(roots), row, dtype=np.int64),
            np.zeros(len(roots), np.int64),
            mass[order].astype(np.int64),
        )

    def _idf_norms(self, r: _Relabelled, log_n: float) -> tuple[float, np.ndarray]:
        """Self-similarities of the query and of every stored graph under the IDF with the query."""
        p, n = self.idf_power, len(self)
        known = r.roots >= 0
        df = np.ones(len(r.roots), dtype=np.int64)
        df[known] += self._df.view()[r.roots[known]]
        query = float((r.root_mass * _idf_weight(log_n, df, p)).sum())
        mass, a1 = self._mass.view(), self._log_mass.view()
        if p == 1:
            stored = mass * log_n - a1
        else:
            stored = mass * log_n**2 - 2.0 * log_n * a1 + self._log2_mass.view()
        roots = r.roots[known]
        old = self._df.view()[roots]
        owner, graphs, q = self._gather_roots(roots)
        if known.all():  # the roots of a graph being added: ``_store_roots`` reads the same postings
            self._gathered = (r.roots, (owner, graphs, q))
        if len(graphs):
            seen = old > 0
            change = np.zeros(len(roots))
            change[seen] = _idf_weight(log_n, old[seen] + 1, p) - _idf_weight(log_n, old[seen], p)
            stored = stored + np.bincount(graphs, q * change[owner], minlength=n)
        return query, np.maximum(stored, 0.0)

    def _scores(self, r: _Relabelled) -> np.ndarray:
        n = len(self)
        postings = self._postings
        # Chains created by this graph have no postings yet.
        stored = r.chains < len(postings.size)
        chains, runs, counts = r.chains[stored], r.runs[stored], r.counts[stored]
        owner, position = _ranges(postings.start.view()[chains], postings.size.view()[chains])
        shared = np.minimum(runs[owner], postings.run.view()[position])
        weights = (counts[owner] * postings.count.view()[position] * shared).astype(np.float64)
        if self.idf_power:
            # Every shared chain's root is one of the query's: its df with the query is df + 1.
            log_n = float(np.log(n + 1))
            df = self._df.view()[self._chain_root.view()[chains]] + 1
            weights *= _idf_weight(log_n, df, self.idf_power)[owner]
            query, stored_norms = self._idf_norms(r, log_n)
            norms = np.sqrt(query * stored_norms)
        else:
            norms = np.sqrt(r.self_similarity * self._self_similarity.view())
        raw = np.bincount(postings.graph.view()[position], weights=weights, minlength=n)
        out = np.zeros(n, dtype=np.float64)
        np.divide(raw, norms, out=out, where=norms > 0)
        return out

    # -- checkpoints ---------------------------------------------------------------------------

    def state(self) -> dict[str, np.ndarray]:
        """All state as flat arrays (``np.savez``-able); ``from_state`` restores it."""
        signatures = list(self._signatures.items())
        key_data = b"".join(key for key, _ in signatures)
        chains, graphs, runs, counts = self._postings.listed()
        idf: dict[str, np.ndarray] = {}
        if self.idf_power:
            root_chains, root_graphs, _, root_counts = self._root_postings.listed()
            idf = {
                "chain_root": self._chain_root.view().copy(),
                "df": self._df.view().copy(),
                "root_posting_chains": root_chains,
                "root_posting_graphs": root_graphs,
                "root_posting_counts": root_counts,
                "mass": self._mass.view().copy(),
                "log_mass": self._log_mass.view().copy(),
                "log2_mass": self._log2_mass.view().copy(),
            }
        return {
            **idf,
            "idf_power": np.array([self.idf_power], dtype=np.int64),
            "iterations": np.array([self.iterations], dtype=np.int64),
            "initial_keys": np.array(list(self._initial.keys()), dtype=np.int64),
            "initial_values": np.array(list(self._initial.values()), dtype=np.int64),
            "signature_data": np.frombuffer(key_data, dtype=np.int64).copy(),
            "signature_sizes": np.array([len(key) // 8 for key, _ in signatures], dtype=np.int64),
            "signature_values": np.array([v for _, v in signatures], dtype=np.int64),
            "chain_length": self._chain_length.view().copy(),
            "chain_anchor": self._chain_anchor.view().copy(),
            "trajectory_keys": self._trajectory_keys.view().copy(),
            "trajectory_bases": self._trajectory_bases.view().copy(),
            "adjacency_ptr": self._adjacency_ptr.view().copy(),
            "adjacency": self._adjacency.view().copy(),
            "ready": self._ready.view().copy(),
            "self_similarity": self._self_similarity.view().copy(),
            "posting_chains": chains,
            "posting_graphs": graphs,
            "posting_runs": runs,
            "posting_counts": counts,
        }

    @classmethod
    def from_state(cls, state: Mapping[str, np.ndarray]) -> WLKernel:
        idf_power = int(state["idf_power"][0]) if "idf_power" in state else 0
        kernel = cls(int(state["iterations"][0]), idf_power)
        kernel._initial = dict(
            zip(state["initial_keys"].tolist(), state["initial_values"].tolist(), strict=True)
        )
        data = np.ascontiguousarray(state["signature_data"], dtype=np.int64).tobytes()
        sizes = state["signature_sizes"].astype(np.int64)
        begins = (np.cumsum(sizes) - sizes).tolist()
        kernel._signatures = {
            data[8 * b : 8 * (b + z)]: v
            for b, z, v in zip(begins, sizes.tolist(), state["signature_values"].tolist(), strict=True)
        }
        kernel._chain_length = _Buffer(np.int64, state["chain_length"])
        kernel._chain_anchor = _Buffer(np.int64, state["chain_anchor"])
        kernel._trajectory_keys = _Buffer(np.int64, state["trajectory_keys"])
        kernel._trajectory_bases = _Buffer(np.int64, state["trajectory_bases"])
        kernel._adjacency_ptr = _Buffer(np.int64, state["adjacency_ptr"])
        kernel._adjacency = _Buffer(np.int64, state["adjacency"])
        kernel._ready = _Buffer(np.int64, state["ready"])
        kernel._self_similarity = _Buffer(np.float64, state["self_similarity"])
        kernel._postings.add_chains(len(kernel._chain_length))
        kernel._postings.append(
            *(state[f"posting_{name}"].astype(np.int64) for name in ("chains", "graphs", "runs", "counts"))
        )
        if idf_power:
            kernel._chain_root = _Buffer(np.int64, state["chain_root"])
            kernel._df = _Buffer(np.int64, state["df"])
            kernel._root_postings.add_chains(len(kernel._chain_root))
            root_chains = state["root_posting_chains"].astype(np.int64)
            kernel._root_postings.append(
                root_chains,
                state["root_posting_graphs"].astype(np.int64),
                np.zeros(len(root_chains), dtype=np.int64),
                state["root_posting_counts"].astype(np.int64),
            )
            kernel._mass = _Buffer(np.float64, state["mass"])
            kernel._log_mass = _Buffer(np.float64, state["log_mass"])
            kernel._log2_mass = _Buffer(np.float64, state["log2_mass"])
        return kernel


# -- grakel: the exact baseline and test oracle ---------------------------------------------------


def to_grakel(graph: LabelledGraph) -> tuple[dict[int, dict[int, float]], dict[int, int]]:
    """grakel input ``(edge dictionary, node labels)``; every node is a key, isolated ones too."""
    edges: dict[int, dict[int, float]] = {node: {} for node in range(graph.num_nodes)}
    for a, b in np.asarray(graph.edges, dtype=np.int64).reshape(-1, 2).tolist():
        edges[a][b] = 1.0
        edges[b][a] = 1.0
    return edges, dict(enumerate(np.asarray(graph.labels).tolist()))


def grakel_kernel_matrix(graphs: Sequence[LabelledGraph], iterations: int) -> np.ndarray:
    """grakel's normalised WL kernel matrix (h = ``iterations``); graphs without nodes get 0 rows."""
    from grakel.kernels import VertexHistogram, WeisfeilerLehman

    out = np.zeros((len(graphs), len(graphs)))
    keep = [i for i, g in enumerate(graphs) if g.num_nodes > 0]
    if not keep:
        return out
    kernel = (
        WeisfeilerLehman(n_iter=iterations, base_graph_kernel=VertexHistogram, normalize=True)
        if iterations > 0
        else VertexHistogram(normalize=True)
    )
    out[np.ix_(keep, keep)] = kernel.fit_transform([to_grakel(graphs[i]) for i in keep])
    return out


class GrakelWL:
    """The same API on grakel, refitted on every stored graph at each query (slow, exact)."""

    def __init__(self, iterations: int) -> None:
        if iterations < 0:
            raise ValueError(f"iterations must be >= 0, got {iterations}")
        self.iterations = iterations
        self._graphs: list[LabelledGraph] = []

    def __len__(self) -> int:
        return len(self._graphs)

    def add(self, graph: LabelledGraph) -> int:
        self._graphs.append(graph)
        return len(self._graphs) - 1

    def query(self, graph: LabelledGraph) -> np.ndarray:
        if not self._graphs:
            return np.zeros(0)
        return grakel_kernel_matrix([*self._graphs, graph], self.iterations)[-1, :-1]

    def add_and_query(self, graph: LabelledGraph) -> np.ndarray:
        scores = self.query(graph)
        self.add(graph)
        return scores

    def state(self) -> dict[str, np.ndarray]:
        graphs = self._graphs
        edges = [np.asarray(g.edges, np.int64).reshape(-1, 2) for g in graphs]
        return {
            "iterations": np.array([self.iterations], dtype=np.int64),
            "node_counts": np.array([g.num_nodes for g in graphs], dtype=np.int64),
            "edge_counts": np.array([len(e) for e in edges], dtype=np.int64),
            "labels": np.concatenate(
                [np.zeros(0, np.int64), *(np.asarray(g.labels, np.int64) for g in graphs)]
            ),
            "kinds": np.concatenate(
                [np.zeros(0, np.int64), *(np.asarray(g.kinds, np.int64) for g in graphs)]
            ),
            "edges": np.concatenate([np.zeros((0, 2), np.int64), *edges]),
        }

    @classmethod
    def from_state(cls, state: Mapping[str, np.ndarray]) -> GrakelWL:
        kernel = cls(int(state["iterations"][0]))
        nodes = np.cumsum(state["node_counts"])[:-1]
        edges = np.cumsum(state["edge_counts"])[:-1]
        for labels, kinds, pairs in zip(
            np.split(state["labels"], nodes),
            np.split(state["kinds"], nodes),
            np.split(state["edges"].reshape(-1, 2), edges),
            strict=True,
        ):
            kernel.add(LabelledGraph(labels=labels, edges=pairs, kinds=kinds))
        return kernel
