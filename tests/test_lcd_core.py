"""Graph builder, label matching, temporal constraint and LCD metrics on known inputs."""

from __future__ import annotations

import numpy as np
import pytest

from eval.lcd_metrics import (
    gt_references,
    has_reachable_loop,
    is_true_match,
    loop_pose_error,
    precision_recall_curve,
    summarise,
)
from frontends.types import DetectedObject
from lcd.graph import AROUND, BACKGROUND, DISTANCE, INSIDE, OBJECT, SCENE, GraphConfig, build_graph
from lcd.label_matching import LabelMatchConfig, match_labels


def _obj(label: str, box: tuple[float, float, float, float]) -> DetectedObject:
    return DetectedObject(label, 0.9, box)


OBJECTS = [
    _obj("chair", (100, 100, 200, 200)),
    _obj("tv", (300, 100, 400, 180)),
    _obj("cup", (150, 300, 180, 330)),
]
KEYPOINTS = np.array(
    [[150, 150], [120, 110], [350, 150], [210, 150], [160, 320], [600, 400], [10, 10], [320, 240]],
    dtype=np.float32,
)
WORDS = np.arange(len(KEYPOINTS))


def test_three_tier_graph_structure() -> None:
    graph = build_graph(KEYPOINTS, WORDS, OBJECTS, GraphConfig(margin_px=25))
    sizes = graph.tier_sizes()
    assert sizes["scene"] == 1 and sizes["object"] == 3 and sizes["distance"] == 3
    # inside boxes: (150,150) (120,110) in the chair, (350,150) in the tv, (160,320) in the cup
    assert sizes["tier2"] == 4
    # within 25 px of a box edge but outside it: (210,150) next to the chair
    assert sizes["tier3"] == 1
    # (600,400), (10,10), (320,240) belong to no object: background on the scene node
    assert sizes["tier0"] == 3
    nx_graph = graph.to_networkx()
    assert nx_graph.number_of_nodes() == graph.num_nodes
    # every feature hangs off exactly one anchor; objects meet each other only through distance nodes
    for node, data in nx_graph.nodes(data=True):
        if data["kind"] in ("tier2", "tier3", "tier0"):
            assert nx_graph.degree(node) == 1
        if data["kind"] == "distance":
            assert {nx_graph.nodes[n]["kind"] for n in nx_graph.neighbors(node)} == {"object"}


def test_tier2_labels_carry_the_object_class_and_tier3_do_not() -> None:
    tiered = build_graph(
        KEYPOINTS, np.zeros(len(KEYPOINTS), dtype=int), OBJECTS, GraphConfig(feature_label="tier")
    )
    inside = set(tiered.labels[tiered.kinds == INSIDE].tolist())
    around = set(tiered.labels[tiered.kinds == AROUND].tolist())
    assert len(inside) == 3  # chair, tv, cup: the same word, three classes
    assert len(around) == 1


def test_word_labels_reach_the_class_through_the_anchor() -> None:
    """Default: a feature's own label is its word; its anchor's class joins at WL iteration 1."""
    graph = build_graph(KEYPOINTS, np.zeros(len(KEYPOINTS), dtype=int), OBJECTS)
    features = np.isin(graph.kinds, [INSIDE, AROUND, BACKGROUND])
    assert len(set(graph.labels[features].tolist())) == 1
    anchors: dict[int, set[int]] = {}
    for a, b in graph.edges.tolist():
        for feature, anchor in ((a, b), (b, a)):
            if graph.kinds[feature] == INSIDE:
                anchors.setdefault(feature, set()).add(int(graph.labels[anchor]))
    # the three boxes' features hang off three differently labelled anchors
    assert len({frozenset(v) for v in anchors.values()}) == 3


def test_ablations_and_no_objects() -> None:
    two = build_graph(KEYPOINTS, WORDS, OBJECTS, GraphConfig(tiers=2))
    assert (two.kinds == AROUND).sum() == 0
    flat = build_graph(KEYPOINTS, WORDS, OBJECTS, GraphConfig(tiers=1))
    assert set(flat.kinds.tolist()) == {SCENE, BACKGROUND} and (flat.kinds == BACKGROUND).sum() == len(
        KEYPOINTS
    )
    empty = build_graph(KEYPOINTS, WORDS, [])
    assert (empty.kinds == OBJECT).sum() == 0 and (empty.kinds == BACKGROUND).sum() == len(KEYPOINTS)
    nothing = build_graph(np.zeros((0, 2)), np.zeros(0, dtype=int), [])
    assert nothing.num_nodes == 1 and len(nothing.edges) == 0


def test_distance_bins_are_scale_invariant() -> None:
    scaled = [DetectedObject(o.label, o.score, tuple(2 * v for v in o.box)) for o in OBJECTS]  # type: ignore[misc]
    a = build_graph(KEYPOINTS, WORDS, OBJECTS)
    b = build_graph(KEYPOINTS * 2, WORDS, scaled)
    assert sorted(a.labels[a.kinds == DISTANCE].tolist()) == sorted(b.labels[b.kinds == DISTANCE].tolist())


def test_label_matching_tolerates_40_percent_missing() -> None:
    labels = ["chair", "tv", "cup", "book", "bottle"]
    rng = np.random.default_rng(0)
    boxes = [(x, y, x + 40, y + 40) for x, y in rng.uniform(0, 500, size=(5, 2))]
    full = [_obj(lab, box) for lab, box in zip(labels, boxes, strict=True)]
    # the same layout seen from farther away (scale 0.5) and shifted, with 2 of 5 objects missed
    far = [
        _obj(o.label, (o.box[0] / 2 + 80, o.box[1] / 2 + 30, o.box[2] / 2 + 80, o.box[3] / 2 + 30))
        for o in full
    ]
    match = match_labels(full, far[:3])
    assert match.ratio == pytest.approx(3 / 5) and match.agrees(LabelMatchConfig())
    # a different arrangement of the same labels does not agree
    shuffled = [_obj(o.label, full[(i + 2) % 5].box) for i, o in enumerate(full)]
    assert not match_labels(full, shuffled).agrees(LabelMatchConfig())
    assert match_labels(full, []).ratio == 0.0


def test_metrics_known_answers() -> None:
    refs = gt_references(np.array([[10, 2], [11, 3], [10, 1]]))
    assert refs[10].tolist() == [1, 2] and refs[11].tolist() == [3] and set(refs) == {10, 11}
    # Any order, with repeats: each query's references, sorted.
    pairs = np.random.default_rng(0).integers(0, 50, (500, 2))
    expected: dict[int, list[int]] = {}
    for query, ref in pairs.tolist():
        expected.setdefault(query, []).append(ref)
    found = {q: r.tolist() for q, r in gt_references(pairs).items()}
    assert found == {q: sorted(r) for q, r in expected.items()}
    assert gt_references(np.zeros((0, 2), dtype=np.int64)) == {}  # a scene without revisits
    assert is_true_match(3, refs[10], tolerance=1) and not is_true_match(4, refs[10], tolerance=1)
    assert has_reachable_loop(refs[11], [0, 5], tolerance=2) and not has_reachable_loop(refs[11], [6], 2)
    scores = np.array([0.9, 0.8, 0.7, 0.6, 0.5])
    correct = np.array([True, True, False, True, False])
    thresholds, precision, recall = precision_recall_curve(scores, correct, positives=4)
    np.testing.assert_allclose(thresholds, scores)
    np.testing.assert_allclose(precision, [1, 1, 2 / 3, 3 / 4, 3 / 5])
    np.testing.assert_allclose(recall, [0.25, 0.5, 0.5, 0.75, 0.75])
    figures = summarise(scores, correct, positives=4, threshold=0.75)
    assert figures["recall_at_100p"] == 0.5 and figures["threshold_at_100p"] == 0.8
    assert figures["precision"] == 1.0 and figures["recall"] == 0.5
    assert figures["auc_pr"] == pytest.approx(0.25 * 1 + 0.25 * 1 + 0.25 * 0.75)
    # tied scores are accepted together
    _, tied_precision, _ = precision_recall_curve(np.array([0.5, 0.5]), np.array([True, False]), 1)
    np.testing.assert_allclose(tied_precision, [0.5])


def _pose(yaw_deg: float, position: tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    pose = np.eye(4)
    pose[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    pose[:3, 3] = position
    return pose


def test_loop_pose_error_compares_rotation_and_direction_not_scale() -> None:
    match, query = _pose(10, (1.0, 0.0, 2.0)), _pose(30, (2.0, 0.0, 2.5))
    truth = np.linalg.inv(match) @ query
    sim3 = truth.copy()
    sim3[:3, :3] *= 4.0  # a map at another scale: same loop
    sim3[:3, 3] *= 4.0
    error = loop_pose_error(match, query, sim3)
    assert error.rotation_deg < 1e-6 and error.direction_deg < 1e-6 and not error.wrong
    assert error.baseline_m == pytest.approx(np.hypot(1.0, 0.5))
    turned = truth.copy()
    turned[:3, :3] = _pose(8, (0, 0, 0))[:3, :3] @ truth[:3, :3]
    assert loop_pose_error(match, query, turned).rotation_deg == pytest.approx(8.0)
    assert loop_pose_error(match, query, turned).wrong
    backwards = truth.copy()
    backwards[:3, 3] *= -1
    assert loop_pose_error(match, query, backwards).direction_deg == pytest.approx(180.0)
    assert loop_pose_error(match, query, backwards).wrong
    # Cameras 5 cm apart: the direction is noise, only the rotation decides.
    near = _pose(30, (1.03, 0.0, 2.04))
    flipped = np.linalg.inv(match) @ near
    flipped[:3, 3] *= -1
    assert not loop_pose_error(match, near, flipped).wrong
