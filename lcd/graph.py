"""The SymbioLCD2 keyframe graph: semantic objects as anchors, ORB features around them.

Paper, section III-D: tier 1 connects the objects to each other (edge feature: normalised
distance), tier 2 connects the ORB features inside a box to its object and gives them the object's
label, tier 3 connects the features within ``x`` px outside the box edges to the object, unlabelled.

Our interpretation of what the paper leaves open (measured in docs/paper-interpretation.md):
- WL needs discrete labels. An object node is labelled by its class. A feature node is labelled by
  its visual word (the "vBoW" node feature; ``SymbioLCD2Config.word_level`` picks the tree level).
  Tier 2 "inherits the object's label" through its edge: WL's first iteration relabels a feature
  by (word, its anchor's class), so features of the same word in the same kind of object match
  from iteration 1 on. Putting the class (and the tier) into the feature's own label instead
  (``feature_label="tier"``) makes one missed detection change the labels of all the features in
  the box, and measured worse with 30 % missed objects (docs/paper-interpretation.md).
- WL ignores edge labels, so each object-object edge is split by a node labelled with the
  normalised distance bin (the standard edge-label-to-node transform); distances are divided by
  the mean distance between the objects of the image, which makes them scale invariant.
- A feature inside several boxes joins each of them (the object filter drops heavy overlaps).
- With too few objects (< ``min_objects``) the paper's graph is empty or trivial. Every graph
  therefore also has a scene node joined to the objects and to the features outside all boxes
  (tier 0, word labels), so a keyframe without objects degrades to a vBoW-like star graph instead
  of matching nothing. ``background=False`` drops it (the paper's literal graph).
- ``tiers``: 1 = flat ablation (features only: every feature joins the scene node, no objects),
  2 = objects + features inside boxes, 3 = the full graph.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import networkx as nx
import numpy as np

from frontends.types import DetectedObject

# Node kinds, the top bits of every label: labels of different kinds never collide.
SCENE, OBJECT, INSIDE, AROUND, BACKGROUND, DISTANCE = 1, 2, 3, 4, 5, 6
_KIND_NAMES = {
    SCENE: "scene",
    OBJECT: "object",
    INSIDE: "tier2",
    AROUND: "tier3",
    BACKGROUND: "tier0",
    DISTANCE: "distance",
}


@dataclass(frozen=True)
class GraphConfig:
    #: 1 = flat (features only), 2 = objects + features in boxes, 3 = + features within ``margin_px``.
    tiers: int = 3
    #: The paper's x: features up to this many pixels outside a box edge join tier 3.
    margin_px: float = 25.0
    #: Edges between objects become nodes labelled with one of this many normalised-distance bins.
    distance_bins: int = 4
    #: Upper edge of the last distance bin, in units of the mean object-object distance.
    max_normalised_distance: float = 2.0
    #: Experimental: False drops the scene node of the features outside every box (the paper's literal graph).
    background: bool = True
    #: Fewer objects than this: the keyframe is counted as object-poor (reported, not rejected).
    min_objects: int = 2
    #: Experimental: feature label: word, or tier (word + tier + class) (docs/2026-12-06-config-evidence.md)
    feature_label: Literal["word", "tier"] = "word"


@dataclass(frozen=True)
class LabelledGraph:
    """A node-labelled undirected graph in the compact form the WL kernel consumes."""

    #: One int64 label per node.
    labels: np.ndarray
    #: (E, 2) int64 node index pairs, each undirected edge once.
    edges: np.ndarray
    #: Node kind per node (SCENE, OBJECT, ...), for sizes and drawing.
    kinds: np.ndarray

    @property
    def num_nodes(self) -> int:
        return len(self.labels)

    def tier_sizes(self) -> dict[str, int]:
        return {name: int((self.kinds == kind).sum()) for kind, name in _KIND_NAMES.items()}

    def to_networkx(self) -> nx.Graph:
        graph = nx.Graph()
        for node, (label, kind) in enumerate(zip(self.labels.tolist(), self.kinds.tolist(), strict=True)):
            graph.add_node(node, label=label, kind=_KIND_NAMES[kind])
        graph.add_edges_from(self.edges.tolist())
        return graph


def class_code(label: str) -> int:
    """A stable 32-bit code of a class name (the same in every process, unlike ``hash``)."""
    return zlib.crc32(label.encode("utf-8"))


def node_label(kind: int, class_name: str | None = None, word: int = 0) -> int:
    """Pack (kind, class, word) into one int64: kind in bits 56+, class in 24..55, word below."""
    code = class_code(class_name) if class_name is not None else 0
    return (kind << 56) | (code << 24) | (int(word) & 0xFFFFFF)


def _words_labels(kind: int, words: np.ndarray, class_name: str | None) -> np.ndarray:
    base = node_label(kind, class_name, 0)
    return base | (words.astype(np.int64) & 0xFFFFFF)


def _feature_labels(kind: int, words: np.ndarray, class_name: str | None, config: GraphConfig) -> np.ndarray:
    if config.feature_label == "word":
        return _words_labels(BACKGROUND, words, None)
    return _words_labels(kind, words, class_name)


def build_graph(
    keypoints: np.ndarray,
    words: np.ndarray,
    objects: Sequence[DetectedObject],
    config: GraphConfig = GraphConfig(),
) -> LabelledGraph:
    """The keyframe graph of ``keypoints`` (N, 2) px with visual ``words`` (N,) and filtered ``objects``."""
    keypoints = np.asarray(keypoints, dtype=np.float64).reshape(-1, 2)
    words = np.asarray(words, dtype=np.int64).reshape(-1)
    if len(keypoints) != len(words):
        raise ValueError(f"{len(keypoints)} keypoints but {len(words)} words")
    use_objects = config.tiers >= 2
    labels: list[np.ndarray] = [np.array([node_label(SCENE)], dtype=np.int64)]
    kinds: list[np.ndarray] = [np.array([SCENE])]
    edges: list[np.ndarray] = []
    count = 1

    def add_nodes(node_labels: np.ndarray, kind: int) -> np.ndarray:
        nonlocal count
        ids = np.arange(count, count + len(node_labels), dtype=np.int64)
        labels.append(node_labels.astype(np.int64))
        kinds.append(np.full(len(node_labels), kind))
        count += len(node_labels)
        return ids

    attached = np.zeros(len(keypoints), dtype=bool)
    if use_objects and objects:
        boxes = np.array([o.box for o in objects], dtype=np.float64)
        object_ids = add_nodes(
            np.array([node_label(OBJECT, o.label) for o in objects], dtype=np.int64), OBJECT
        )
        edges.append(np.column_stack([np.zeros(len(object_ids), dtype=np.int64), object_ids]))
        edges.extend(_object_distance_edges(boxes, object_ids, config, add_nodes))
        x, y = keypoints[:, 0], keypoints[:, 1]
        for obj, box, object_id in zip(objects, boxes, object_ids, strict=True):
            inside = (x >= box[0]) & (x < box[2]) & (y >= box[1]) & (y < box[3])
            members: list[tuple[np.ndarray, int, str | None]] = [(np.flatnonzero(inside), INSIDE, obj.label)]
            if config.tiers >= 3:
                m = config.margin_px
                near = (x >= box[0] - m) & (x < box[2] + m) & (y >= box[1] - m) & (y < box[3] + m) & ~inside
                members.append((np.flatnonzero(near), AROUND, None))
            for indices, kind, class_name in members:
                if indices.size == 0:
                    continue
                ids = add_nodes(_feature_labels(kind, words[indices], class_name, config), kind)
                edges.append(np.column_stack([np.full(len(ids), object_id), ids]))
                attached[indices] = True
    if config.background or not use_objects:
        loose = np.flatnonzero(~attached)
        if loose.size:
            ids = add_nodes(_feature_labels(BACKGROUND, words[loose], None, config), BACKGROUND)
            edges.append(np.column_stack([np.zeros(len(ids), dtype=np.int64), ids]))
    return LabelledGraph(
        labels=np.concatenate(labels),
        edges=np.concatenate(edges) if edges else np.zeros((0, 2), dtype=np.int64),
        kinds=np.concatenate(kinds),
    )


def _object_distance_edges(
    boxes: np.ndarray,
    object_ids: np.ndarray,
    config: GraphConfig,
    add_nodes: Callable[[np.ndarray, int], np.ndarray],
) -> list[np.ndarray]:
    """Tier 1: every pair of objects, joined through a node labelled with their distance bin."""
    if len(boxes) < 2:
        return []
    centres = np.column_stack([(boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2])
    first, second = np.triu_indices(len(boxes), k=1)
    distances = np.linalg.norm(centres[first] - centres[second], axis=1)
    scale = distances.mean()
    normalised = distances / scale if scale > 0 else np.zeros_like(distances)
    bins = np.minimum(
        (normalised / config.max_normalised_distance * config.distance_bins).astype(np.int64),
        config.distance_bins - 1,
    )
    middle = add_nodes(np.array([node_label(DISTANCE, None, b) for b in bins], dtype=np.int64), DISTANCE)
    return [
        np.column_stack([object_ids[first], middle]),
        np.column_stack([middle, object_ids[second]]),
    ]
