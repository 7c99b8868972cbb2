"""The incremental WL kernel (lcd.wl) against grakel, its oracle, and its state handling."""

from __future__ import annotations

import numpy as np
import pytest

from lcd.graph import LabelledGraph
from lcd.wl import GrakelWL, WLKernel, grakel_kernel_matrix

ITERATIONS = (0, 1, 3, 10, 50)


def random_graph(rng: np.random.Generator, nodes: int, alphabet: int, density: float) -> LabelledGraph:
    labels = rng.integers(0, alphabet, nodes).astype(np.int64) * 1_000_003  # large, sparse label values
    first, second = np.triu_indices(nodes, k=1)
    keep = rng.random(len(first)) < density
    edges = np.column_stack([first[keep], second[keep]]).astype(np.int64)
    return LabelledGraph(labels=labels, edges=edges.reshape(-1, 2), kinds=np.zeros(nodes, dtype=np.int64))


def star_graph(rng: np.random.Generator, objects: int, alphabet: int) -> LabelledGraph:
    """A small keyframe-like graph: scene node, objects, distance nodes, feature leaves."""
    labels, edges = [0], []
    object_ids = []
    for _ in range(objects):
        object_ids.append(len(labels))
        edges.append((0, len(labels)))
        labels.append(100 + int(rng.integers(0, 3)))
    for a in range(len(object_ids)):
        for b in range(a + 1, len(object_ids)):
            middle = len(labels)
            labels.append(200 + int(rng.integers(0, 2)))
            edges += [(object_ids[a], middle), (middle, object_ids[b])]
    for parent in [0, *object_ids]:
        for _ in range(int(rng.integers(0, 8))):
            edges.append((parent, len(labels)))
            labels.append(300 + int(rng.integers(0, alphabet)))
    return LabelledGraph(
        labels=np.array(labels, dtype=np.int64),
        edges=np.array(edges, dtype=np.int64).reshape(-1, 2),
        kinds=np.zeros(len(labels), dtype=np.int64),
    )


def path_graph(nodes: int, tail: int = 0, cycle: bool = False) -> LabelledGraph:
    """Uniform labels on a path (or cycle) with a pendant ``tail`` of another label: two such graphs
    keep equal labels for a while after both partitions are final, then diverge."""
    edges = [(i, i + 1) for i in range(nodes - 1)] + ([(nodes - 1, 0)] if cycle else [])
    edges += [(nodes - 1 + i, nodes + i) for i in range(tail)]
    labels = np.array([7] * nodes + [8] * tail, dtype=np.int64)
    return LabelledGraph(
        labels=labels,
        edges=np.array(edges, dtype=np.int64).reshape(-1, 2),
        kinds=np.zeros(len(labels), dtype=np.int64),
    )


def graph_set(seed: int) -> list[LabelledGraph]:
    """Random graphs of every awkward kind, star graphs, and repeats (which follow stored chains)."""
    rng = np.random.default_rng(seed)
    graphs = [
        random_graph(rng, 1, 2, 0.0),  # one node
        random_graph(rng, 6, 2, 0.0),  # no edges
        LabelledGraph(  # isolated nodes, two components, a duplicate edge and a self-loop
            labels=np.array([1, 1, 2, 2, 1, 3], dtype=np.int64),
            edges=np.array([[0, 1], [1, 0], [2, 3], [3, 3]], dtype=np.int64),
            kinds=np.zeros(6, dtype=np.int64),
        ),
    ]
    graphs += [
        random_graph(rng, int(rng.integers(2, 14)), int(rng.integers(1, 5)), float(rng.uniform(0.05, 0.5)))
        for _ in range(10)
    ]
    graphs += [star_graph(rng, int(rng.integers(0, 4)), 3) for _ in range(8)]
    paths = [
        path_graph(n, tail, cycle) for n in range(3, 13) for tail in (0, 1, 2) for cycle in (False, True)
    ]
    order = rng.permutation(len(paths))[:30]
    return [*graphs, *graphs[3:9], *graphs[-4:], *(paths[i] for i in order), *paths[:4]]


@pytest.mark.parametrize("iterations", ITERATIONS)
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_grakel(iterations: int, seed: int) -> None:
    graphs = graph_set(seed)
    reference = grakel_kernel_matrix(graphs, iterations)
    kernel = WLKernel(iterations)
    for row, graph in enumerate(graphs):
        scores = kernel.add_and_query(graph)
        assert scores.shape == (row,)
        np.testing.assert_allclose(scores, reference[row, :row], rtol=0, atol=1e-9)
    # Every stored graph against the full store, including itself.
    for row, graph in enumerate(graphs):
        np.testing.assert_allclose(kernel.query(graph), reference[row], rtol=0, atol=1e-9)
    # Unseen graphs (labels missing from the dictionary) against a partial store.
    half = len(graphs) // 2
    partial = WLKernel(iterations)
    for graph in graphs[:half]:
        partial.add(graph)
    for row in range(half, len(graphs)):
        np.testing.assert_allclose(partial.query(graphs[row]), reference[row, :half], rtol=0, atol=1e-9)


def test_grakel_backend_is_the_oracle() -> None:
    graphs = graph_set(2)[:12]
    reference = grakel_kernel_matrix(graphs, 3)
    backend = GrakelWL(3)
    for row, graph in enumerate(graphs):
        np.testing.assert_allclose(backend.add_and_query(graph), reference[row, :row], atol=1e-12)
    restored = GrakelWL.from_state(backend.state())
    np.testing.assert_allclose(restored.query(graphs[0]), reference[0], atol=1e-12)


def test_query_does_not_change_state() -> None:
    graphs = graph_set(3)
    kernel = WLKernel(5)
    for graph in graphs[:15]:
        kernel.add(graph)
    before = kernel.state()
    first = [kernel.query(g) for g in graphs]
    after = kernel.state()
    assert before.keys() == after.keys()
    for key in before:
        np.testing.assert_array_equal(before[key], after[key], err_msg=key)
    np.testing.assert_array_equal(np.concatenate(first), np.concatenate([kernel.query(g) for g in graphs]))
    assert len(kernel) == 15


def test_add_returns_rows_and_add_equals_add_and_query() -> None:
    graphs = graph_set(4)
    plain, scoring = WLKernel(10), WLKernel(10)
    for row, graph in enumerate(graphs):
        assert plain.add(graph) == row
        scoring.add_and_query(graph)
    for graph in graphs:
        np.testing.assert_array_equal(plain.query(graph), scoring.query(graph))


def test_state_round_trip() -> None:
    graphs = graph_set(5)
    kernel = WLKernel(50)
    for graph in graphs[:20]:
        kernel.add(graph)
    restored = WLKernel.from_state({k: v.copy() for k, v in kernel.state().items()})
    assert len(restored) == 20
    for graph in graphs[20:]:
        np.testing.assert_array_equal(kernel.add_and_query(graph), restored.add_and_query(graph))


def test_deterministic() -> None:
    graphs = graph_set(6)
    runs = []
    for _ in range(2):
        kernel = WLKernel(50)
        runs.append(np.concatenate([kernel.add_and_query(g) for g in graphs]))
    np.testing.assert_array_equal(runs[0], runs[1])


def test_empty_graph_scores_zero() -> None:
    empty = LabelledGraph(
        labels=np.zeros(0, dtype=np.int64),
        edges=np.zeros((0, 2), dtype=np.int64),
        kinds=np.zeros(0, dtype=np.int64),
    )
    graphs = graph_set(7)[:5]
    kernel = WLKernel(50)
    assert kernel.query(empty).shape == (0,)
    assert kernel.add_and_query(empty).shape == (0,)
    for graph in graphs:
        scores = kernel.add_and_query(graph)
        assert np.isfinite(scores).all() and scores[0] == 0.0
    np.testing.assert_array_equal(kernel.query(empty), np.zeros(len(kernel)))
    assert GrakelWL(2).query(empty).shape == (0,)


def test_bad_input() -> None:
    with pytest.raises(ValueError):
        WLKernel(-1)
    bad = LabelledGraph(
        labels=np.zeros(2, dtype=np.int64),
        edges=np.array([[0, 2]], dtype=np.int64),
        kinds=np.zeros(2, dtype=np.int64),
    )
    with pytest.raises(ValueError):
        WLKernel(2).add(bad)


def test_follower_stops_when_the_anchors_neighbour_changes_chain() -> None:
    """Found by random search: the query follows a stored chain whose anchor's neighbour leaves its
    own chain later; filling the remaining iterations early would overcount."""
    stored = [
        ([0, 1, 0, 0, 0], [[0, 1], [0, 2], [1, 3], [1, 4]]),
        ([0] * 7, [[0, 1], [0, 2], [2, 3], [3, 4], [4, 5], [3, 6]]),
        ([0] * 10, [[0, 1], [0, 2], [2, 3], [0, 4], [1, 5], [3, 6], [0, 7], [2, 8], [7, 9]]),
        ([0, 0], [[0, 1]]),
        ([0, 1, 1, 1, 1], [[0, 1], [1, 2], [2, 3], [1, 4]]),
        ([0, 0, 0, 0, 1, 1], [[0, 1], [1, 2], [2, 3], [3, 4], [0, 5]]),
        ([1, 0, 1, 0, 1, 1, 0, 1], [[0, 1], [0, 2], [0, 3], [1, 4], [3, 5], [5, 6], [3, 7]]),
        ([0] * 8, [[0, 1], [1, 2], [1, 3], [3, 4], [3, 5], [3, 6], [3, 7]]),
        ([0, 0, 0, 1, 1, 0, 0, 0, 0], [[0, 1], [0, 2], [1, 3], [0, 4], [4, 5], [4, 6], [6, 7], [0, 8]]),
    ]
    graphs = [
        LabelledGraph(np.array(labels, np.int64), np.array(edges, np.int64), np.zeros(len(labels), np.int64))
        for labels, edges in stored
    ]
    reference = grakel_kernel_matrix(graphs, 12)
    kernel = WLKernel(12)
    for graph in graphs[:-1]:
        kernel.add(graph)
    np.testing.assert_allclose(kernel.query(graphs[-1]), reference[-1, :-1], rtol=0, atol=1e-9)


def test_query_stops_following_at_the_stable_iteration() -> None:
    """Found by random search: the query's partition becomes final at the iteration where its
    follower's neighbour drops out, so the early stop must use the final classes' neighbours."""
    stored = LabelledGraph(
        np.array([1, 0, 1, 1, 0, 0], np.int64),
        np.array([[0, 1], [0, 2], [2, 3], [0, 4], [4, 5]], np.int64),
        np.zeros(6, np.int64),
    )
    query = LabelledGraph(
        np.array([1, 1, 1, 1, 1, 0, 1, 0], np.int64),
        np.array([[0, 1], [0, 2], [2, 3], [2, 4], [0, 5], [4, 6], [2, 7]], np.int64),
        np.zeros(8, np.int64),
    )
    kernel = WLKernel(5)
    kernel.add(stored)
    expected = grakel_kernel_matrix([stored, query], 5)[1, :1]
    np.testing.assert_allclose(kernel.query(query), expected, rtol=0, atol=1e-9)
