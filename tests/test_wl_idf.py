"""The IDF-weighted WL kernel (``WLKernel(h, idf_power=p)``) against a brute-force reference."""

from __future__ import annotations

import numpy as np
import pytest
from test_wl import graph_set, star_graph

from lcd.graph import LabelledGraph
from lcd.wl import WLKernel


class Reference:
    """Explicit WL relabelling with one dictionary per iteration shared by every graph, and the
    weighted kernel computed from the full label histograms (the definition in ``lcd.wl``)."""

    def __init__(self, iterations: int) -> None:
        self.iterations = iterations
        self.dictionaries: list[dict[tuple[int, tuple[int, ...]], int]] = [{} for _ in range(iterations)]

    def histograms(self, graph: LabelledGraph) -> list[dict[tuple[int, int], int]]:
        """Per iteration: (root input label, label) -> count."""
        n = graph.num_nodes
        neighbours: list[set[int]] = [set() for _ in range(n)]
        for a, b in np.asarray(graph.edges, dtype=np.int64).reshape(-1, 2).tolist():
            neighbours[a].add(b)
            neighbours[b].add(a)
        roots = [int(v) for v in np.asarray(graph.labels).tolist()]
        labels = list(roots)
        out = []
        for t in range(self.iterations + 1):
            if t:
                dictionary = self.dictionaries[t - 1]
                keys = [(labels[v], tuple(sorted(labels[u] for u in neighbours[v]))) for v in range(n)]
                labels = [dictionary.setdefault(key, len(dictionary)) for key in keys]
            histogram: dict[tuple[int, int], int] = {}
            for root, label in zip(roots, labels, strict=True):
                histogram[(root, label)] = histogram.get((root, label), 0) + 1
            out.append(histogram)
        return out

    @staticmethod
    def kernel(
        a: list[dict[tuple[int, int], int]], b: list[dict[tuple[int, int], int]], weight: dict[int, float]
    ) -> float:
        return sum(
            weight[key[0]] * count * hb.get(key, 0)
            for ha, hb in zip(a, b, strict=True)
            for key, count in ha.items()
        )


def reference_scores(
    graphs: list[LabelledGraph], stored: int, query: LabelledGraph, h: int, p: int
) -> np.ndarray:
    """Normalised weighted kernel of ``query`` against ``graphs[:stored]``; IDF over them and the query."""
    reference = Reference(h)
    histograms = [reference.histograms(g) for g in graphs[:stored]]
    mine = reference.histograms(query)
    df: dict[int, int] = {}
    for graph in [*graphs[:stored], query]:
        for root in set(np.asarray(graph.labels).tolist()):
            df[root] = df.get(root, 0) + 1
    n = stored + 1
    weight = {root: float(np.log(n / count)) ** p for root, count in df.items()}
    own = Reference.kernel(mine, mine, weight)
    out = np.zeros(stored)
    for row, histogram in enumerate(histograms):
        norm = np.sqrt(own * Reference.kernel(histogram, histogram, weight))
        out[row] = Reference.kernel(mine, histogram, weight) / norm if norm > 0 else 0.0
    return out


@pytest.mark.parametrize("power", [1, 2])
@pytest.mark.parametrize("iterations", [0, 1, 3, 10])
def test_matches_reference(iterations: int, power: int) -> None:
    graphs = graph_set(11)
    kernel = WLKernel(iterations, idf_power=power)
    for row, graph in enumerate(graphs):
        scores = kernel.add_and_query(graph)
        np.testing.assert_allclose(
            scores, reference_scores(graphs, row, graph, iterations, power), rtol=1e-9, atol=1e-9
        )
    # A query does not depend on being stored: unseen graphs against a partial store.
    half = len(graphs) // 2
    partial = WLKernel(iterations, idf_power=power)
    for graph in graphs[:half]:
        partial.add(graph)
    for row in range(half, len(graphs), 3):
        np.testing.assert_allclose(
            partial.query(graphs[row]),
            reference_scores(graphs, half, graphs[row], iterations, power),
            rtol=1e-9,
            atol=1e-9,
        )


def word_graph(words: list[int]) -> LabelledGraph:
    """A keyframe-like star: a scene node (label 0) joined to one leaf per visual word."""
    labels = np.array([0, *words], dtype=np.int64)
    edges = np.column_stack([np.zeros(len(words), dtype=np.int64), np.arange(1, len(words) + 1)])
    return LabelledGraph(labels, edges.astype(np.int64), np.zeros(len(labels), dtype=np.int64))


def test_rare_words_outrank_a_frequent_word() -> None:
    """Stored: one keyframe shares two rare words with the query, another shares (three times) the
    frequent word that almost every keyframe holds; both have four words of their own. The plain
    kernel prefers the frequent word; the IDF kernel prefers the rare words."""
    frequent, rare = 1, [2, 3]
    fillers = [word_graph([frequent, 100 + i, 200 + i]) for i in range(16)]
    rare_match = word_graph([*rare, 500, 501, 502, 503])
    frequent_match = word_graph([frequent] * 3 + [700, 701, 702, 703])
    query = word_graph([*rare, frequent, frequent, frequent, 600])
    database = [*fillers, rare_match, frequent_match]
    results = {}
    for power in (0, 1, 2):
        kernel = WLKernel(3, idf_power=power)
        for graph in database:
            kernel.add(graph)
        scores = kernel.query(query)
        results[power] = scores[len(fillers)] - scores[len(fillers) + 1]
    assert results[0] < 0
    assert results[1] > 0
    assert results[2] > 0


def test_state_round_trip_and_determinism() -> None:
    graphs = graph_set(12) + [star_graph(np.random.default_rng(3), 3, 4) for _ in range(5)]
    kernel = WLKernel(10, idf_power=2)
    for graph in graphs[:25]:
        kernel.add(graph)
    state = kernel.state()
    assert int(state["idf_power"][0]) == 2
    restored = WLKernel.from_state({k: v.copy() for k, v in state.items()})
    assert restored.idf_power == 2 and len(restored) == 25
    for graph in graphs[25:]:
        np.testing.assert_array_equal(kernel.add_and_query(graph), restored.add_and_query(graph))
    after, again = kernel.state(), restored.state()
    assert after.keys() == again.keys()
    for key in after:
        np.testing.assert_array_equal(after[key], again[key], err_msg=key)


def test_query_leaves_idf_state_alone() -> None:
    graphs = graph_set(13)
    kernel = WLKernel(5, idf_power=1)
    for graph in graphs[:15]:
        kernel.add(graph)
    before = kernel.state()
    for graph in graphs:
        kernel.query(graph)
    after = kernel.state()
    for key in before:
        np.testing.assert_array_equal(before[key], after[key], err_msg=key)


def test_plain_state_has_no_idf_arrays_and_old_states_load() -> None:
    kernel = WLKernel(3)
    for graph in graph_set(14)[:10]:
        kernel.add(graph)
    state = kernel.state()
    assert "df" not in state and int(state["idf_power"][0]) == 0
    old = {k: v for k, v in state.items() if k != "idf_power"}  # a checkpoint from before the option
    restored = WLKernel.from_state(old)
    assert restored.idf_power == 0
    probe = graph_set(14)[12]
    np.testing.assert_array_equal(kernel.query(probe), restored.query(probe))


def test_bad_power() -> None:
    with pytest.raises(ValueError):
        WLKernel(3, idf_power=3)
