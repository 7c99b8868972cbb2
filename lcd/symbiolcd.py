"""SymbioLCD (Kim et al., IROS 2021): vBoW candidates re-scored by a Random Forest over object cues.

The SymbioLCD2 paper's baseline. Per keyframe: its ORB descriptors become a TF-IDF BoW vector
scored with DBoW2's L1 score against every earlier keyframe through the inverted index (like
``vbow``), and its objects are filtered like SymbioLCD2's (``lcd.objects.filtering``). The
``shortlist`` earlier keyframes with the highest vBoW scores outside the temporal window are
compared object by object in SymbioLCD's scale-invariant normalised plane
(``lcd.label_matching.match_labels``). Each (query, candidate) pair becomes one row of
``FEATURE_NAMES``:

- ``vbow``: the raw L1 score; ``vbow_relative``: it divided by the query's best shortlisted score;
- ``label_ratio``: label-matched objects / objects of the larger set;
- ``hausdorff``: the modified Hausdorff distance between the normalised object layouts;
- ``query_objects``, ``candidate_objects``: how many objects each keyframe kept after filtering.

A scikit-learn ``RandomForestClassifier`` gives each row its loop probability, which is the
candidate's score; candidates come best first (ties keep the vBoW order).

Our interpretation where the paper leaves a choice open:

- Training data. The paper trains on labelled pairs of its own sequences. We train on pairs from
  synthetic scenes this project renders (``symbio symbiolcd-train``; seeds 110-115, never the
  evaluation seeds 0-99 nor real evaluation images); the shipped table ``data/symbiolcd_rf.npz``
  is documented in ``lcd/data/README.md``. A shortlisted pair is positive when it is a GT loop
  pair. The table holds features and labels, not a pickled model: the forest is refit at
  construction (deterministic with ``seed``, about 0.4 s) and survives scikit-learn upgrades.
- Which pairs are scored: the top ``shortlist`` vBoW candidates, the rows the table was built from.
- Vocabulary: the shipped tree by default, the one the table's vBoW features came from; the online
  vocabulary's scores lie on another scale (docs/2026-12-06-online-vocabulary.md).
- Monotonic constraints (``monotonic``): the probability may only rise with ``vbow``,
  ``vbow_relative`` and ``label_ratio`` and only fall with ``hausdorff``. An unconstrained forest
  saturates where most training pairs are loops and then ranks by noise; leave-one-scene-out on
  the six training scenes (tolerance 3) gave mean recall at 100 % precision 0.07 and PR-AUC 0.54
  unconstrained, 0.39 / 0.65 constrained, 0.44 / 0.68 constrained with ``vbow_relative``
  (raw vBoW: 0.46 / 0.68). The time between the keyframes was tried as a feature and dropped: the
  forest used it most, i.e. learnt when the training scenes happen to revisit.
- Fewer than two objects on a side leave the normalised plane undefined: the Hausdorff feature is
  then ``NO_LAYOUT_HAUSDORFF``, above every real distance, and the label ratio comes from labels
  alone (``match_labels``).
- The temporal constraint is the window: the last ``temporal_window`` keyframes (counted by
  arrival, like ``vbow``) are never candidates. Keyframes with fewer than ``min_features`` ORB
  features neither query nor get matched: their BoW vectors say nothing about the place.
- ``threshold`` 0.5 is the forest's own decision (a loop is more likely than not).
"""

from __future__ import annotations

import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from frontends.config import load_config
from frontends.errors import ConfigError, InputFileError
from frontends.types import DetectedObject, Keyframe
from lcd.base import LoopCandidate
from lcd.label_matching import match_labels
from lcd.objects.filtering import FilterConfig, filter_objects
from lcd.online_vocabulary import OnlineVocabulary, OnlineVocabularyConfig
from lcd.vbow import open_vocabulary
from lcd.vocabulary import BowDatabase, Vocabulary, empty_bow

if TYPE_CHECKING:
    from sklearn.ensemble import RandomForestClassifier

#: The training table shipped with the package (see ``lcd/data/README.md``).
DEFAULT_TABLE = Path(__file__).resolve().parent / "data" / "symbiolcd_rf.npz"
TABLE_FORMAT = "symbiolcd-rf-table"
TABLE_VERSION = 1
FEATURE_NAMES = (
    "vbow",
    "vbow_relative",
    "label_ratio",
    "hausdorff",
    "query_objects",
    "candidate_objects",
)
#: Per feature: +1 = the loop probability may only rise with it, -1 = only fall, 0 = free.
MONOTONIC = (1, 1, 1, -1, 0, 0)
#: The Hausdorff feature of a pair without two objects on each side; real distances stay below it
#: (unit-RMS layouts of a few dozen objects are a few units apart at most).
NO_LAYOUT_HAUSDORFF = 10.0


@dataclass(frozen=True)
class SymbioLCDConfig:
    #: Random Forest seed: the same seed and table give the same forest.
    seed: int = 0
    #: A candidate whose loop probability reaches this counts as a loop.
    threshold: float = 0.5
    #: The last this many keyframes before the query are never candidates.
    temporal_window: int = 20
    #: At most this many candidates per query, best first.
    max_candidates: int = 5
    #: How many top vBoW candidates the forest scores.
    shortlist: int = 10
    #: Keyframes with fewer ORB features neither query nor get matched.
    min_features: int = 20
    #: Trees in the Random Forest.
    n_estimators: int = 100
    #: Depth limit of each tree; 0 = unlimited.
    max_depth: int = 8
    #: Fewest training rows in a leaf of each tree.
    min_samples_leaf: int = 5
    #: Constrain the forest to ``MONOTONIC`` (see the module docstring).
    monotonic: bool = True
    #: The object filter applied before the objects are compared (``FilterConfig``).
    objects: FilterConfig = field(default_factory=FilterConfig)
    #: "online" = built from the sequence (``online``), a tree ``.npz``, or empty = the shipped tree.
    vocabulary: str = ""
    #: The online vocabulary's settings (with ``vocabulary: online``).
    online: OnlineVocabularyConfig = field(default_factory=OnlineVocabularyConfig)
    #: Training table ``.npz`` (``symbio symbiolcd-train``); empty = the shipped default.
    model: str = ""

    def __post_init__(self) -> None:
        if self.temporal_window < 0 or self.max_depth < 0:
            raise ConfigError("symbiolcd: temporal_window and max_depth must be >= 0")
        if min(self.max_candidates, self.shortlist, self.n_estimators, self.min_samples_leaf) < 1:
            raise ConfigError(
                "symbiolcd: max_candidates, shortlist, n_estimators and min_samples_leaf must be >= 1"
            )


@dataclass(frozen=True)
class Shortlist:
    """One query's shortlisted earlier keyframes (best vBoW first) and their feature rows."""

    matches: np.ndarray
    features: np.ndarray


@dataclass(frozen=True)
class TrainingTable:
    features: np.ndarray
    labels: np.ndarray


def pair_features(
    vbow_score: float,
    best_vbow_score: float,
    query_objects: Sequence[DetectedObject],
    candidate_objects: Sequence[DetectedObject],
) -> np.ndarray:
    """One row of ``FEATURE_NAMES`` for a (query, candidate) pair."""
    match = match_labels(query_objects, candidate_objects)
    return np.array(
        [
            vbow_score,
            vbow_score / best_vbow_score,
            match.ratio,
            min(match.hausdorff, NO_LAYOUT_HAUSDORFF),
            len(query_objects),
            len(candidate_objects),
        ],
        dtype=np.float64,
    )


def image_size_of(keyframe: Keyframe) -> tuple[int, int]:
    """(width, height) of the keyframe's image; without one, the keypoints' extent bounds it."""
    if keyframe.image is not None:
        return keyframe.image.shape[1], keyframe.image.shape[0]
    extent = keyframe.keypoints.max(axis=0) + 1 if len(keyframe.keypoints) else np.ones(2)
    return int(extent[0]), int(extent[1])


class ShortlistBuilder:
    """The vBoW database and the filtered objects of every keyframe: each query's feature rows.

    Shared by the detector and by ``symbio symbiolcd-train``, so the forest is trained on exactly
    the rows it later scores.
    """

    def __init__(self, config: SymbioLCDConfig, vocabulary: Vocabulary | OnlineVocabulary) -> None:
        self.config = config
        self.vocabulary = vocabulary
        self._database = BowDatabase()
        self._ids: list[int] = []
        self._objects: list[list[DetectedObject]] = []
        self._matchable: list[bool] = []

    def add(self, keyframe: Keyframe) -> Shortlist:
        config = self.config
        descriptors = keyframe.descriptors
        earlier = len(self._ids)
        if isinstance(self.vocabulary, OnlineVocabulary):
            # The online vocabulary is its own inverted index (scores under the current IDF).
            scores = self.vocabulary.add_and_query(descriptors)[1]
        else:
            bow = self.vocabulary.transform(descriptors) if len(descriptors) else empty_bow()
            scores = self._database.query(bow)
            self._database.add(bow)
        objects = filter_objects(keyframe.objects, image_size_of(keyframe), config.objects)
        enough_features = len(keyframe.keypoints) >= config.min_features
        self._ids.append(keyframe.id)
        self._objects.append(objects)
        self._matchable.append(enough_features)
        last = earlier - config.temporal_window
        if not enough_features or last <= 0:
            return Shortlist(np.zeros(0, np.int64), np.zeros((0, len(FEATURE_NAMES))))
        eligible = np.flatnonzero(np.asarray(self._matchable[:last]) & (scores[:last] > 0))
        best = eligible[np.argsort(-scores[eligible], kind="stable")[: config.shortlist]]
        rows = [pair_features(scores[k], scores[best[0]], objects, self._objects[k]) for k in best]
        features = np.array(rows).reshape(len(best), len(FEATURE_NAMES))
        return Shortlist(np.array([self._ids[k] for k in best], dtype=np.int64), features)


def load_table(path: str | Path) -> TrainingTable:
    """A training table written by ``symbio symbiolcd-train``; anything else is an ``InputFileError``."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except FileNotFoundError:
        raise InputFileError(path, "SymbioLCD training table not found") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise InputFileError(path, f"not a SymbioLCD training table (.npz): {exc}") from None
    missing = {"format", "version", "feature_names", "features", "labels"} - arrays.keys()
    if missing:
        raise InputFileError(path, f"not a SymbioLCD training table: missing {sorted(missing)}")
    found = f"{arrays['format']!s} version {arrays['version']!s}"
    if found != f"{TABLE_FORMAT} version {TABLE_VERSION}":
        raise InputFileError(path, f"expected a {TABLE_FORMAT} version {TABLE_VERSION}, got {found}")
    names = tuple(str(name) for name in arrays["feature_names"])
    if names != FEATURE_NAMES:
        raise InputFileError(
            path, f"feature columns {list(names)} differ from this detector's {list(FEATURE_NAMES)}"
        )
    features, labels = arrays["features"], arrays["labels"]
    if features.ndim != 2 or features.shape[1] != len(FEATURE_NAMES) or labels.shape != features.shape[:1]:
        raise InputFileError(
            path, f"features {features.shape} and labels {labels.shape} do not form one row per pair"
        )
    if not np.issubdtype(features.dtype, np.number) or not np.isfinite(features).all():
        raise InputFileError(path, "features must be finite numbers")
    if not np.isin(labels, (0, 1)).all() or len(np.unique(labels)) != 2:
        raise InputFileError(path, "labels must be 0 or 1, with pairs of both kinds")
    return TrainingTable(features.astype(np.float64), labels.astype(np.int64))


def save_table(path: str | Path, table: TrainingTable, provenance: dict[str, Any]) -> None:
    """Write a training table; ``provenance`` (scalars) records how it was made."""
    arrays: dict[str, Any] = {
        "format": np.array(TABLE_FORMAT),
        "version": np.array(TABLE_VERSION),
        "feature_names": np.array(FEATURE_NAMES),
        "features": table.features.astype(np.float32),
        "labels": table.labels.astype(np.uint8),
    }
    arrays.update({f"provenance_{key}": np.array(value) for key, value in provenance.items()})
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    # Through a handle: np.savez would append ".npz" to any other suffix.
    with target.open("wb") as handle:
        np.savez_compressed(handle, **arrays)


def fit_forest(table: TrainingTable, config: SymbioLCDConfig) -> RandomForestClassifier:
    # Imported here: scikit-learn costs ~120 MB, which commands that never fit a forest do not pay.
    from sklearn.ensemble import RandomForestClassifier

    forest = RandomForestClassifier(
        n_estimators=config.n_estimators,
        max_depth=config.max_depth or None,
        min_samples_leaf=config.min_samples_leaf,
        random_state=config.seed,
        monotonic_cst=list(MONOTONIC) if config.monotonic else None,
        n_jobs=1,
    )
    return forest.fit(table.features, table.labels)


class SymbioLCD:
    """vBoW shortlist re-scored by a Random Forest; see the module docstring."""

    name = "symbiolcd"

    def __init__(
        self,
        config: SymbioLCDConfig = SymbioLCDConfig(),
        vocabulary: Vocabulary | OnlineVocabulary | None = None,
        table: TrainingTable | None = None,
    ) -> None:
        self.config = config
        self.threshold = config.threshold
        self.temporal_window = config.temporal_window
        if vocabulary is None:
            vocabulary = open_vocabulary(config.vocabulary, config.online)
        if table is None:
            table = load_table(config.model or DEFAULT_TABLE)
        self.forest = fit_forest(table, config)
        self._positive_column = int(np.flatnonzero(self.forest.classes_ == 1)[0])
        self._shortlists = ShortlistBuilder(config, vocabulary)

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]:
        shortlist = self._shortlists.add(keyframe)
        if len(shortlist.matches) == 0:
            return []
        probability = self.forest.predict_proba(shortlist.features)[:, self._positive_column]
        order = np.argsort(-probability, kind="stable")[: self.config.max_candidates]
        candidates = []
        for k in order:
            row = dict(zip(FEATURE_NAMES, shortlist.features[k].tolist(), strict=True))
            components = {key: row[key] for key in ("vbow", "label_ratio", "hausdorff")}
            components["rf"] = float(probability[k])
            candidates.append(
                LoopCandidate(keyframe.id, int(shortlist.matches[k]), float(probability[k]), components)
            )
        return candidates


def create(overrides: Sequence[str] = (), config_path: Any = None) -> SymbioLCD:
    """The registry's factory: ``SymbioLCDConfig`` from defaults, a YAML file and ``key=value`` overrides."""
    return SymbioLCD(load_config(SymbioLCDConfig, config_path, overrides))
