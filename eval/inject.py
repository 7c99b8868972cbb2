"""Fault injection for ``symbio run --inject KIND[:RATE][,KIND[:RATE]...] [--inject-seed N]``.

A debug option and the fixture of ``tests/test_faults.py``: it makes a run meet the bad inputs and
failing plugins a long recording meets, and the run must handle each as documented
(docs/what-we-test-against.md). ``RATE`` is the fraction of frames (frame faults) or of calls (plugin faults)
hit, each chosen by a generator seeded with (``--inject-seed``, fault, frame or keyframe ids), so
the same spec gives the same faults on the same frames. A frame gets at most one frame fault (the
first listed that hits it).

Frame faults wrap the dataset (``InjectedDataset``) and go through the reader's own code: the clean
image is read, the faulty version is encoded to a temporary file and the file is decoded by
``Dataset.read_image`` exactly as a file on disk would be (so an undecodable one is skipped and
counted with a warning naming the index file and line, or is an error with ``--strict``):

* ``corrupt-image``: 64 bytes in the middle of the PNG overwritten with noise;
* ``truncated-image``: the PNG cut after half its bytes;
* ``wrong-size``: the image at half its width and height (a frame from another camera mode);
* ``black``, ``overexposed`` (3 x intensity + 100, clipped), ``blur`` (31 px linear motion blur),
  ``no-features`` (the image's mean grey everywhere): images that decode and starve the frontend;
* ``duplicate-timestamp``, ``backwards-timestamp``: the frame's timestamp set to the previous
  frame's, or one frame interval before it (``Dataset.__iter__`` skips and counts such frames).

Plugin faults wrap the loop-closing components (``Injection.wrap_plugins``):

* ``objects-empty``, ``objects-raise``: the object detector finds nothing, or raises;
* ``loops-raise``: the loop detector raises;
* ``false-loops``: the loop detector proposes, with a high score, only wrong pairs: an earlier
  keyframe whose GT camera centre is at least ``FALSE_LOOP_MIN_DISTANCE`` from the query's
  (without GT: any keyframe at least ``FALSE_LOOP_MIN_GAP`` keyframes back); the real
  detector still sees every keyframe, its candidates are dropped;
* ``false-loops-verified``: the same wrong pairs, and the verifier passes each as verified with a
  plausible constraint (the query at the match's place: identity Sim(3), the covariance of a good
  verification), as perceptual aliasing would: what is left to reject them is the backend's PCM + GNC;
* ``verifier-raise``: the verifier raises;
* ``verifier-timeout``: the verifier answers only after 1.25 x ``loop_closing.verify_timeout_s``
  (set a small budget, e.g. ``--set loop_closing.verify_timeout_s=0.2``, to keep the run short).

How many faults were injected, per kind, is ``faults_injected_<kind>`` in ``metrics.json``.
"""

from __future__ import annotations

import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from frontends.datasets import Dataset
from frontends.errors import ConfigError, SymbioError
from frontends.types import DetectedObject, Frame, Keyframe
from lcd.base import LoopCandidate, LoopDetector, ObjectDetector

if TYPE_CHECKING:  # the run's CLI lists KINDS without loading gtsam and pycolmap
    from slam_backend.pipeline import LoopClosing
    from slam_backend.verify import Verification, Verifier

IMAGE_FAULTS = (
    "corrupt-image", "truncated-image", "wrong-size", "black", "overexposed", "blur", "no-features"
)  # fmt: skip
TIMESTAMP_FAULTS = ("duplicate-timestamp", "backwards-timestamp")
FRAME_FAULTS = IMAGE_FAULTS + TIMESTAMP_FAULTS
OBJECT_FAULTS = ("objects-empty", "objects-raise")
FALSE_LOOP_FAULTS = ("false-loops", "false-loops-verified")
LOOP_FAULTS = ("loops-raise", *FALSE_LOOP_FAULTS)
VERIFIER_FAULTS = ("verifier-raise", "verifier-timeout", "false-loops-verified")
KINDS = tuple(dict.fromkeys(FRAME_FAULTS + OBJECT_FAULTS + LOOP_FAULTS + VERIFIER_FAULTS))
#: The rate of a fault given without one.
DEFAULT_RATES = {
    **dict.fromkeys(FRAME_FAULTS, 0.05),
    **dict.fromkeys(OBJECT_FAULTS, 0.3),
    "loops-raise": 0.2,
    "false-loops": 1.0,
    "false-loops-verified": 1.0,
    "verifier-raise": 0.3,
    "verifier-timeout": 0.3,
}
#: A false loop joins keyframes whose GT camera centres are at least this far apart (m) ...
FALSE_LOOP_MIN_DISTANCE = 2.0
#: ... or, without GT, at least this many keyframes apart.
FALSE_LOOP_MIN_GAP = 10
#: Score of a false loop, as a multiple of the detector's threshold: far above any threshold.
FALSE_LOOP_SCORE = 10.0
#: An injected slow verifier answers after this multiple of the verification budget.
TIMEOUT_FACTOR = 1.25
#: Sigmas of a fabricated verified false loop: rotation (rad), translation (fraction of the match's
#: median point depth), log-scale; the pycolmap verifier's floors, i.e. a confident constraint.
FALSE_LOOP_SIGMAS = (0.003, 0.01, 0.02)


class InjectedFault(SymbioError):
    """Raised by a plugin wrapper on purpose (``objects-raise``, ``loops-raise``, ``verifier-raise``)."""


@dataclass(frozen=True)
class Fault:
    kind: str
    rate: float


@dataclass(frozen=True)
class InjectionSpec:
    faults: tuple[Fault, ...]
    seed: int = 0

    @classmethod
    def parse(cls, text: str, seed: int = 0) -> InjectionSpec:
        """``KIND[:RATE][,KIND[:RATE]...]``; a bad kind or rate is a ``ConfigError`` naming it."""
        faults: list[Fault] = []
        for item in (part.strip() for part in text.split(",")):
            kind, colon, rate_text = item.partition(":")
            if kind not in KINDS:
                raise ConfigError(f"--inject {text!r}: unknown fault {kind!r} (one of {', '.join(KINDS)})")
            try:
                rate = float(rate_text) if colon else DEFAULT_RATES[kind]
            except ValueError:
                raise ConfigError(
                    f"--inject {text!r}: rate of {kind} is not a number: {rate_text!r}"
                ) from None
            if not 0 < rate <= 1:
                raise ConfigError(f"--inject {text!r}: rate of {kind} must be in (0, 1], got {rate_text}")
            if any(f.kind == kind for f in faults):
                raise ConfigError(f"--inject {text!r}: {kind} given twice")
            if kind in FALSE_LOOP_FAULTS and any(f.kind in FALSE_LOOP_FAULTS for f in faults):
                raise ConfigError(f"--inject {text!r}: give one of {' and '.join(FALSE_LOOP_FAULTS)}")
            faults.append(Fault(kind, rate))
        return cls(tuple(faults), seed)

    def rate(self, kind: str) -> float:
        return next((f.rate for f in self.faults if f.kind == kind), 0.0)

    def hits(self, kind: str, *key: int) -> bool:
        """Whether fault ``kind`` hits the item ``key`` (frame index, or keyframe ids)."""
        rate = self.rate(kind)
        return rate > 0 and np.random.default_rng([self.seed, KINDS.index(kind), *key]).random() < rate

    def frame_fault(self, index: int) -> str | None:
        return next(
            (f.kind for f in self.faults if f.kind in FRAME_FAULTS and self.hits(f.kind, index)), None
        )


class Injection:
    """One run's faults: wraps its dataset and plugins, and counts what it injected (``counts``)."""

    def __init__(self, spec: InjectionSpec) -> None:
        self.spec = spec
        self.counts: Counter[str] = Counter()
        #: (query, match) keyframe ids of the false loops proposed so far.
        self.false_pairs: set[tuple[int, int]] = set()

    def wrap_dataset(self, dataset: Dataset) -> InjectedDataset:
        return InjectedDataset(dataset, self)

    def wrap_plugins(self, closing: LoopClosing, dataset: Dataset) -> None:
        """Replace ``closing``'s object detector, loop detector and verifier by faulty wrappers, for
        the plugin faults of the spec; a fault whose plugin the run does not have is an error."""
        kinds = {f.kind for f in self.spec.faults}
        plugins = ((OBJECT_FAULTS, closing.objects), (LOOP_FAULTS, closing.detector))
        for names, present in (*plugins, (VERIFIER_FAULTS, closing.verifier)):
            wanted = kinds & set(names)
            if wanted and present is None:
                raise ConfigError(
                    f"--inject {', '.join(sorted(wanted))}: this run has no such plugin (--no-loops?)"
                )
        if closing.objects is not None and kinds & set(OBJECT_FAULTS):
            closing.objects = FaultyObjectDetector(closing.objects, self)
        if closing.detector is not None and kinds & set(LOOP_FAULTS):
            closing.detector = FaultyLoopDetector(closing.detector, self, gt_centres(dataset))
        if closing.verifier is not None and kinds & set(VERIFIER_FAULTS):
            closing.verifier = FaultyVerifier(
                closing.verifier, self, TIMEOUT_FACTOR * closing.config.verify_timeout_s
            )

    def figures(self) -> dict[str, int]:
        """``faults_injected_<kind>`` (dashes as underscores) for each fault of the spec."""
        return {f"faults_injected_{f.kind.replace('-', '_')}": self.counts[f.kind] for f in self.spec.faults}

    def hit(self, kind: str, *key: int) -> bool:
        """``spec.hits``, counted."""
        if self.spec.hits(kind, *key):
            self.counts[kind] += 1
            return True
        return False


def gt_centres(dataset: Dataset) -> np.ndarray | None:
    """GT camera centre per frame (NaN where there is none); None without GT."""
    return None if dataset.gt_poses is None else dataset.gt_poses[:, :3, 3]


class InjectedDataset(Dataset):
    """``dataset`` with the frame faults of ``injection`` (see the module docstring)."""

    def __init__(self, dataset: Dataset, injection: Injection) -> None:
        entries = list(dataset.entries)
        self.image_faults: dict[int, str] = {}
        self.timestamp_faults: dict[int, str] = {}
        for index in range(len(entries)):
            kind = injection.spec.frame_fault(index)
            if kind in IMAGE_FAULTS:
                self.image_faults[index] = kind
            elif kind is not None and index > 0:
                previous = entries[index - 1].timestamp
                step = dataset.entries[index].timestamp - dataset.entries[index - 1].timestamp
                stamp = previous if kind == "duplicate-timestamp" else previous - step
                entries[index] = replace(entries[index], timestamp=stamp)
                self.timestamp_faults[index] = kind
        super().__init__(
            dataset.root,
            dataset.camera,
            entries,
            gt_poses=dataset.gt_poses,
            gt_loop_pairs=dataset.gt_loop_pairs,
            strict=dataset.strict,
            notes=dataset.notes,
        )
        self.format_name = dataset.format_name  # type: ignore[misc]  # the wrapped reader's name
        self.inner = dataset
        self.injection = injection
        self.skipped = dataset.skipped  # one record of skipped frames, whoever skips them
        self._folder = tempfile.TemporaryDirectory(prefix="symbio-inject-")

    def __iter__(self) -> Iterator[Frame]:
        """The frames, counting each timestamp fault once the stream has passed its frame."""
        pending = sorted(self.timestamp_faults.items())
        for frame in super().__iter__():
            while pending and pending[0][0] < frame.index:
                self.injection.counts[pending.pop(0)[1]] += 1
            yield frame
        self.injection.counts.update(kind for _, kind in pending)

    def read_image(self, index: int) -> np.ndarray | None:
        """The reader's image; for a faulted frame, its faulty file decoded like any other file."""
        image = self.inner.read_image(index)
        kind = self.image_faults.get(index)
        if kind is None or image is None:
            return image
        self.injection.counts[kind] += 1
        entry = self.entries[index]
        path = Path(self._folder.name) / f"{index:06d}-{kind}.png"
        rng = np.random.default_rng([self.injection.spec.seed, KINDS.index(kind), index, 1])
        path.write_bytes(faulty_png(kind, image, rng))
        self.entries[index] = replace(entry, path=path)
        try:
            return super().read_image(index)
        finally:
            self.entries[index] = entry
            path.unlink()


def faulty_png(kind: str, image: np.ndarray, rng: np.random.Generator) -> bytes:
    """The bytes of a PNG file showing fault ``kind`` of ``image``."""
    if kind == "black":
        image = np.zeros_like(image)
    elif kind == "overexposed":
        image = cv2.convertScaleAbs(image, alpha=3.0, beta=100)
    elif kind == "blur":
        kernel = np.full((1, 31), 1 / 31, dtype=np.float32)
        image = cv2.filter2D(image, -1, kernel, borderType=cv2.BORDER_REFLECT)
    elif kind == "wrong-size":
        image = cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2), interpolation=cv2.INTER_AREA)
    elif kind == "no-features":
        image = np.full_like(image, round(float(image.mean())))
    ok, encoded = cv2.imencode(".png", image)
    assert ok, "PNG encoding of a decoded image cannot fail"
    data = bytearray(encoded.tobytes())
    if kind == "corrupt-image":
        start = len(data) // 3
        data[start : start + 64] = rng.integers(0, 256, 64, dtype=np.uint8).tobytes()
    elif kind == "truncated-image":
        del data[len(data) // 2 :]
    return bytes(data)


class FaultyObjectDetector:
    """``objects-raise``: raises on the frame; ``objects-empty``: finds nothing in it."""

    def __init__(self, inner: ObjectDetector, injection: Injection) -> None:
        self.inner = inner
        self.injection = injection
        self.name = inner.name

    def detect(self, image: np.ndarray, frame: Frame | None = None) -> list[DetectedObject]:
        index = frame.index if frame is not None else -1
        if self.injection.hit("objects-raise", index):
            raise InjectedFault(f"injected objects-raise on frame {index}")
        found = self.inner.detect(image, frame)
        return [] if self.injection.hit("objects-empty", index) else found


class FaultyLoopDetector:
    """``loops-raise``: raises on the keyframe; ``false-loops``: proposes only a wrong pair."""

    def __init__(self, inner: LoopDetector, injection: Injection, centres: np.ndarray | None) -> None:
        self.inner = inner
        self.injection = injection
        self.centres = centres
        self.name = inner.name
        self.threshold = inner.threshold
        if hasattr(inner, "proposal_threshold"):
            self.proposal_threshold = inner.proposal_threshold
        #: (keyframe id, frame index) of every keyframe seen.
        self.seen: list[tuple[int, int]] = []

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]:
        kind = next((f.kind for f in self.injection.spec.faults if f.kind in FALSE_LOOP_FAULTS), None)
        far = (k for k, frame in self.seen if self._far(frame, keyframe.frame_index, k, keyframe.id))
        wrong = list(far) if kind is not None else []
        self.seen.append((keyframe.id, keyframe.frame_index))
        if self.injection.hit("loops-raise", keyframe.id):
            raise InjectedFault(f"injected loops-raise on keyframe {keyframe.id}")
        candidates = self.inner.add(keyframe)
        if kind is None:
            return candidates
        if not wrong or not self.injection.hit(kind, keyframe.id):
            return []
        rng = np.random.default_rng([self.injection.spec.seed, KINDS.index(kind), keyframe.id, 1])
        match = wrong[int(rng.integers(len(wrong)))]
        self.injection.false_pairs.add((keyframe.id, match))
        score = FALSE_LOOP_SCORE * max(self.threshold, 0.01)
        return [LoopCandidate(keyframe.id, match, score, {"injected_false_loop": 1.0})]

    def _far(self, frame: int, query_frame: int, keyframe: int, query: int) -> bool:
        if self.centres is not None:
            distance = float(np.linalg.norm(self.centres[frame] - self.centres[query_frame]))
            if np.isfinite(distance):
                return distance >= FALSE_LOOP_MIN_DISTANCE
        return query - keyframe >= FALSE_LOOP_MIN_GAP


class FaultyVerifier:
    """``verifier-raise``: raises on the pair; ``verifier-timeout``: answers after ``delay_s``;
    ``false-loops-verified``: passes the injected false pairs with a fabricated constraint."""

    def __init__(self, inner: Verifier, injection: Injection, delay_s: float) -> None:
        self.inner = inner
        self.injection = injection
        self.delay_s = delay_s
        self.name = inner.name

    def verify(self, query: Keyframe, match: Keyframe) -> Verification:
        if self.injection.hit("verifier-raise", query.id, match.id):
            raise InjectedFault(f"injected verifier-raise on {query.id} -> {match.id}")
        if self.injection.hit("verifier-timeout", query.id, match.id):
            time.sleep(self.delay_s)
        if (
            self.injection.spec.rate("false-loops-verified") > 0
            and (query.id, match.id) in self.injection.false_pairs
        ):
            return fabricated_verification(query, match)
        return self.inner.verify(query, match)


def fabricated_verification(query: Keyframe, match: Keyframe) -> Verification:
    """A verified loop claiming ``query`` stands where ``match`` stood (identity Sim(3)), with the
    covariance of a confident verification (``FALSE_LOOP_SIGMAS``)."""
    from slam_backend.verify import Verification

    depth = 1.0
    if match.points3d is not None:
        depths = match.points3d[:, 2]
        depths = depths[np.isfinite(depths) & (depths > 0)]
        depth = float(np.median(depths)) if len(depths) else depth
    rotation, translation, log_scale = FALSE_LOOP_SIGMAS
    covariance = np.diag(np.r_[np.full(3, rotation), np.full(3, translation * depth), log_scale] ** 2)
    inliers = len(match.keypoints) // 2
    return Verification(query.id, match.id, True, "", len(match.keypoints), inliers, np.eye(4), covariance)
