"""The swappable frontend: turns a stream of frames into posed keyframes.

A frontend consumes frames in order (``track``) and says for each where the camera is (or that it
is lost), and which frames became keyframes. Keyframes carry what the loop detector and the
geometric verifier need: keypoints, ORB descriptors, the 3D map points seen by each keypoint, the
map segment and the odometry covariance. Poses are camera-to-world 4x4 in the frontend's map
frame; a monocular map has an arbitrary scale (fixed by its first baseline).

Implementations register by name (entry-point group ``symbio.frontends``); a factory takes the
camera intrinsics and ``--set key=value`` overrides / a YAML file.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np

from frontends.registry import Registry
from frontends.types import CameraIntrinsics, Frame, Keyframe

TrackingState = Literal["initialising", "tracking", "relocalised", "lost"]


@dataclass(frozen=True)
class PointObservations:
    """The map points a frame was posed from: pixel keypoints (as detected) and their point ids
    (unique within the frame's segment, the ids ``Keyframe.point_ids`` uses)."""

    keypoints: np.ndarray
    point_ids: np.ndarray


@dataclass(frozen=True)
class TrackResult:
    """What a frontend says about one frame."""

    frame_index: int
    timestamp: float
    state: TrackingState
    #: Camera-to-world pose of the frame in the map of ``segment``; None while initialising or lost.
    pose: np.ndarray | None
    segment: int = 0
    #: The keyframe this frame became, if it did.
    keyframe: Keyframe | None = None
    #: Results for earlier frames that this call posed after the fact (e.g. the frames seen while
    #: a monocular map initialised); each replaces the result given for its frame before.
    backfilled: tuple[TrackResult, ...] = ()
    #: What the pose rests on, when the frontend keeps a map (lets the pipeline re-pose the frame
    #: after a global bundle adjustment moved the map).
    observations: PointObservations | None = None


@runtime_checkable
class Frontend(Protocol):
    name: str

    def track(self, frame: Frame) -> TrackResult: ...

    def keyframes(self) -> list[Keyframe]:
        """All keyframes so far, with their latest (e.g. bundle-adjusted) poses."""
        ...


@runtime_checkable
class CorrectableFrontend(Frontend, Protocol):
    """A frontend that can continue from a loop-corrected map (``symbio run`` uses it when offered)."""

    def apply_correction(self, poses: Mapping[int, np.ndarray]) -> None:
        """Move keyframes to ``poses`` (camera-to-world Sim(3) ``[sR, t; 0, 1]`` by keyframe id, in
        the frame of the map the frontend gave), with their map points and the current tracking
        state, so that tracking continues in the corrected map instead of fighting the loop."""
        ...


@runtime_checkable
class SettlingFrontend(Frontend, Protocol):
    """A frontend that keeps refining its newest keyframes' poses after handing them out (a local
    bundle adjustment window): loop closing reads a keyframe's odometry step only once this many
    newer keyframes of its segment exist."""

    @property
    def keyframes_in_flux(self) -> int: ...


@runtime_checkable
class MaskingFrontend(Frontend, Protocol):
    """A frontend that keeps objects which move on their own out of its map (DynaSLAM-style)."""

    def set_dynamic_objects(self, provider: Callable[[Frame], Sequence[Sequence[float]]] | None) -> None:
        """``provider(frame)`` gives the boxes (x0, y0, x1, y1[, may_keep]) of objects that can move
        in a frame the frontend is about to map (a keyframe); features inside them are not mapped.
        ``may_keep`` 1: a vehicle, which the frontend may map when it sees it static (mono-vo's
        geometric check, ``frontends/mono_vo/masking.py``); 0 or absent: always masked."""
        ...


@runtime_checkable
class PrefetchingFrontend(Frontend, Protocol):
    """A frontend that can start a frame's work that needs no tracking state (feature extraction)
    before the frame's turn, on another core."""

    def prefetch(self, frame: Frame) -> None:
        """``frame`` is the next to be tracked after the current one; begin its stateless work."""
        ...


#: Frames a ``PrefetchingFrontend`` hears of ahead of their turn. More than one: while a keyframe's
#: local BA holds the main thread (100-200 ms), the extraction thread runs on through the next
#: frames, which then find their features done (docs/2026-12-07-frame-rate.md).
LOOKAHEAD_FRAMES = 4


def with_lookahead(
    frames: Iterable[Frame], frontend: Frontend, depth: int = LOOKAHEAD_FRAMES
) -> Iterator[Frame]:
    """``frames`` one by one; a ``PrefetchingFrontend`` hears of each frame ``depth`` steps ahead,
    so the next frames' features are extracted while the current one is tracked. Frames already
    read are tracked before an error of the reader ends the run."""
    if not isinstance(frontend, PrefetchingFrontend):
        yield from frames
        return
    iterator = iter(frames)
    ahead: deque[Frame] = deque()
    while True:
        while len(ahead) <= depth:
            try:
                following = next(iterator, None)
            except BaseException:
                yield from ahead  # the frames already read are tracked before the error ends the run
                raise
            if following is None:
                break
            frontend.prefetch(following)
            ahead.append(following)
        if not ahead:
            return
        yield ahead.popleft()


class FrontendFactory(Protocol):
    def __call__(
        self, camera: CameraIntrinsics, overrides: Sequence[str] = (), config_path: Any = None
    ) -> Frontend: ...


FRONTENDS: Registry[FrontendFactory] = Registry(
    "frontend",
    "symbio.frontends",
    {"mono-vo": "frontends.mono_vo:create", "replay": "frontends.replay:create"},
)
