"""The ``vbow`` loop detector: DBoW2 bag-of-words similarity, as ORB-SLAM's loop detection uses it.

Per keyframe: the TF-IDF BoW vector of its ORB descriptors (``lcd.vocabulary``), scored with the
L1 score against every earlier keyframe at once through the inverted index. Candidates are the
earlier keyframes outside the temporal window: more than ``temporal_window`` keyframes back *and*
at least ``time_window`` seconds older (either can be 0). Keyframes are counted by arrival, not by
id, so sparse ids work.

Vocabulary: ``online`` by default, built from the sequence itself (``lcd.online_vocabulary``, its own
inverted index); ``vocabulary=""`` is the shipped tree. RTAB-Map samples 0.977 vs 0.909 recall at
100 % precision, Gardens Point recall@1 0.67 vs 0.40 (docs/2026-12-06-online-vocabulary.md).

Score (``normalise``):
- ``none``: the raw L1 score.
- ``previous``: the raw score divided by the query's score against its previous keyframe(s)
  (the minimum over the last ``normalise_neighbours``): DBoW2's normalised similarity, the stand-in
  for ORB-SLAM's minimum score against the covisible keyframes. A reference below
  ``min_reference`` means the query is unlike its own neighbours (motion blur, a turn); like
  DBoW2 the query then yields no candidates.
Measured (RTAB-Map loop samples, recall at 100 % precision): raw 0.909, ``previous`` 0.841 at
best and 0.00-0.34 in most ORB settings; on synthetic scenes raw was equal or better. With sparse
keyframes the previous keyframe is a poor, noisy reference, so ``none`` is the default.

Defaults: ``temporal_window`` 20 keyframes covers the time a camera needs to leave a place
(3.3 s at a keyframe every 5th frame at 30 fps, about the synthetic scenes' 3 s minimum loop gap;
10 let through near-duplicate false positives on a figure-8 scene: 0.81 vs 0.95 recall at 100 %
precision). ``threshold`` 0.1 on the raw score lies above the best false positive measured on
640x480-class images (0.08-0.094 with about 500-1000 features); raw scores fall with fewer
features per image (a 320x240 scene peaks near 0.03), so set it per camera, or use it with
geometric verification.

Consistency (``consistency`` > 0, ORB-SLAM's covisibility-consistency test): a candidate at or above
``threshold`` forms a group with the keyframes within ``group_radius`` of it (keyframe positions,
standing in for the covisibility graph). A group that overlaps a group of the previous query
inherits its count plus one, otherwise it starts at 0; a query with no candidates clears the
groups. Only candidates whose count reaches ``consistency`` are returned (ORB-SLAM: 3).
Without consistency the ``max_candidates`` best candidates are returned whatever their score, so
an evaluation can sweep the threshold.

Components of each candidate: ``vbow`` (raw L1 score), ``normalised`` (when the reference is
defined) and ``consistency`` (when enabled).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from frontends.config import load_config
from frontends.errors import ConfigError
from frontends.types import Keyframe
from lcd.base import LoopCandidate
from lcd.online_vocabulary import OnlineVocabulary, OnlineVocabularyConfig
from lcd.vocabulary import BowDatabase, BowVector, Vocabulary, empty_bow

#: The vocabulary shipped with the package (see ``lcd/data/README.md``).
DEFAULT_VOCABULARY = Path(__file__).resolve().parent / "data" / "orb_k10_l5.npz"
#: The ``vocabulary`` value that selects the online vocabulary (``lcd.online_vocabulary``).
ONLINE = "online"


def open_vocabulary(choice: str, online: OnlineVocabularyConfig) -> Vocabulary | OnlineVocabulary:
    """A config's ``vocabulary``: ``online`` = a new, empty online vocabulary (``online`` its
    config), empty = the shipped tree, else the path of a tree ``.npz``."""
    if choice == ONLINE:
        return OnlineVocabulary(online)
    return Vocabulary.load(choice or DEFAULT_VOCABULARY)


Normalise = Literal["none", "previous"]


@dataclass(frozen=True)
class VbowConfig:
    #: "online" = built from the sequence (``online``), a tree ``.npz``, or empty = the shipped tree.
    vocabulary: str = ONLINE
    #: The online vocabulary's settings (with ``vocabulary: online``).
    online: OnlineVocabularyConfig = field(default_factory=OnlineVocabularyConfig)
    #: A candidate whose score (raw or normalised, per ``normalise``) reaches this counts as a loop.
    threshold: float = 0.1
    #: The last this many keyframes before the query are never candidates.
    temporal_window: int = 20
    #: Keyframes less than this many seconds older than the query are never candidates.
    time_window: float = 0.0
    #: Experimental: none = raw L1 score; previous = over the query's score vs its previous keyframes.
    normalise: Normalise = "none"
    #: ``previous``: the reference is the minimum score against the last this many keyframes.
    normalise_neighbours: int = 1
    #: ``previous``: a reference score below this gives no candidates (DBoW2's ``min_nss_factor``).
    min_reference: float = 0.005
    #: Consecutive earlier queries whose candidate groups must agree (ORB-SLAM: 3); 0 = off.
    consistency: int = 0
    #: Half-width of a candidate's group in keyframes (for ``consistency``).
    group_radius: int = 2
    #: At most this many candidates per query, best first.
    max_candidates: int = 5

    def __post_init__(self) -> None:
        if self.temporal_window < 0 or self.time_window < 0:
            raise ConfigError("vbow: temporal_window and time_window must be >= 0")
        if self.normalise_neighbours < 1 or self.max_candidates < 1:
            raise ConfigError("vbow: normalise_neighbours and max_candidates must be >= 1")
        if self.consistency < 0 or self.group_radius < 0 or self.min_reference < 0:
            raise ConfigError("vbow: consistency, group_radius and min_reference must be >= 0")


class VbowDetector:
    """Bag-of-words loop detector; see the module docstring."""

    name = "vbow"

    def __init__(
        self, config: VbowConfig = VbowConfig(), vocabulary: Vocabulary | OnlineVocabulary | None = None
    ) -> None:
        self.config = config
        self.threshold = config.threshold
        if vocabulary is None:
            vocabulary = open_vocabulary(config.vocabulary, config.online)
        self.vocabulary = vocabulary
        self._database = BowDatabase()
        self._ids: list[int] = []
        self._position: dict[int, int] = {}
        self._timestamps: list[float] = []
        # Consistency groups of the previous query: centre positions and their counts.
        self._group_centres = np.zeros(0, dtype=np.int64)
        self._group_counts = np.zeros(0, dtype=np.int64)

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]:
        descriptors = keyframe.descriptors
        earlier = len(self._ids)
        if isinstance(self.vocabulary, OnlineVocabulary):
            # The online vocabulary is its own inverted index (scores under the current IDF).
            bow, raw, _ = self.vocabulary.add_and_query(descriptors)
        else:
            bow = self.vocabulary.transform(descriptors) if len(descriptors) else empty_bow()
            raw = self._database.query(bow)
            self._database.add(bow)
        self._position[keyframe.id] = earlier
        self._ids.append(keyframe.id)
        self._timestamps.append(keyframe.timestamp)
        candidates = self._score(keyframe, bow, raw, earlier)
        if self.config.consistency > 0:
            candidates = self._consistent(candidates)
        return candidates[: self.config.max_candidates]

    def _score(
        self, keyframe: Keyframe, bow: BowVector, raw: np.ndarray, earlier: int
    ) -> list[LoopCandidate]:
        config = self.config
        last = earlier - config.temporal_window
        if len(bow) == 0 or last <= 0:
            return []
        eligible = np.arange(last)
        if config.time_window > 0:
            times = np.asarray(self._timestamps[:last])
            eligible = eligible[times <= keyframe.timestamp - config.time_window]
        eligible = eligible[raw[eligible] > 0]
        neighbours = raw[max(0, earlier - config.normalise_neighbours) : earlier]
        reference = float(neighbours.min()) if neighbours.size else 0.0
        has_reference = reference >= config.min_reference and reference > 0
        if config.normalise == "previous":
            if not has_reference:
                return []
            scores = raw[eligible] / reference
        else:
            scores = raw[eligible]
        order = np.argsort(-scores, kind="stable")
        candidates = []
        for position, score in zip(eligible[order], scores[order], strict=True):
            components = {"vbow": float(raw[position])}
            if has_reference:
                components["normalised"] = float(raw[position] / reference)
            candidates.append(LoopCandidate(keyframe.id, self._ids[position], float(score), components))
        return candidates

    def _consistent(self, candidates: list[LoopCandidate]) -> list[LoopCandidate]:
        """ORB-SLAM's consistency test over consecutive queries (module docstring)."""
        above = [c for c in candidates if c.score >= self.threshold]
        centres = np.array([self._position[c.match] for c in above], dtype=np.int64)
        counts = np.zeros(len(centres), dtype=np.int64)
        if len(centres) and len(self._group_centres):
            overlap = np.abs(centres[:, None] - self._group_centres[None, :]) <= 2 * self.config.group_radius
            inherited = np.where(overlap, self._group_counts[None, :] + 1, 0).max(axis=1)
            counts = np.where(overlap.any(axis=1), inherited, 0)
        self._group_centres, self._group_counts = centres, counts
        return [
            LoopCandidate(c.query, c.match, c.score, {**c.components, "consistency": float(n)})
            for c, n in zip(above, counts, strict=True)
            if n >= self.config.consistency
        ]


def create(overrides: Sequence[str] = (), config_path: Any = None) -> VbowDetector:
    """The registry's factory: ``VbowConfig`` from its defaults, a YAML file and ``key=value`` overrides."""
    return VbowDetector(load_config(VbowConfig, config_path, overrides))
