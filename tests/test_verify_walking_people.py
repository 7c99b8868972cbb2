"""A person who walks through both views of a loop: the verifier leaves their keypoints out.

The pairs are revisits of the 9000-frame synthetic loop (seed 2, issue 42's long run), where the
same walking person fills a third of both images. Matched, the person's keypoints agree with one
rigid motion, the person's, and pulled the two-view pose 3-6 deg in rotation and 22-46 deg in
translation direction off the truth; those poses joined map segments wrongly
(docs/2026-12-06-walking-people.md).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from frontends.base import TrackResult
from frontends.orb import detect_orb
from frontends.synth import SynthConfig
from frontends.synth.render import SceneRenderer
from frontends.types import DetectedObject, Frame, Keyframe
from lcd.base import LoopCandidate
from slam_backend.pipeline import LoopClosing, LoopClosingConfig
from slam_backend.posegraph import BackendConfig, GtsamPoseGraph
from slam_backend.verify import PycolmapVerifier, Verification, VerifierConfig, colmap_camera, verify_two_view

#: (query, match) frames of the scene whose two-view pose the person spoiled.
PAIRS = ((7357, 816), (7800, 1284))


@pytest.fixture(scope="module")
def renderer() -> SceneRenderer:
    return SceneRenderer(SynthConfig(trajectory="loop", seed=2, frames=9000))


def _keyframe(renderer: SceneRenderer, frame: int, with_people: bool) -> Keyframe:
    rendered = renderer.frame(frame)
    features = detect_orb(cv2.cvtColor(rendered.image, cv2.COLOR_BGR2GRAY))
    people = tuple(
        DetectedObject("person", 0.9, tuple(float(v) for v in o.box))  # type: ignore[arg-type]
        for o in rendered.objects
        if o.movable
    )
    assert people, f"frame {frame} should see a walking person"
    return Keyframe(
        frame, frame, rendered.timestamp, rendered.pose.copy(), features.keypoints, features.descriptors,
        objects=people if with_people else (),
    )  # fmt: skip


def _errors(pose: np.ndarray, query: Keyframe, match: Keyframe) -> tuple[float, float]:
    """Rotation and translation-direction error (deg) of a match_from_query [R | t] against the GT."""
    truth = np.linalg.inv(match.pose) @ query.pose
    cosine = (np.trace(pose[:, :3].T @ truth[:3, :3]) - 1) / 2
    direction = pose[:, 3] @ truth[:3, 3] / np.linalg.norm(pose[:, 3]) / np.linalg.norm(truth[:3, 3])
    return float(np.degrees(np.arccos(np.clip(cosine, -1, 1)))), float(np.degrees(np.arccos(direction)))


@pytest.mark.parametrize("pair", PAIRS)
def test_walking_people_are_left_out_of_the_two_view_pose(
    renderer: SceneRenderer, pair: tuple[int, int]
) -> None:
    camera = colmap_camera(SynthConfig().intrinsics)
    config = VerifierConfig(planar_pose=True)
    (query, match), (query_seen, match_seen) = (
        [_keyframe(renderer, frame, with_people) for frame in pair] for with_people in (False, True)
    )
    fooled = verify_two_view(query, match, camera, config)
    assert fooled.passed and fooled.match_from_query is not None
    rotation, direction = _errors(fooled.match_from_query, query, match)
    assert rotation > 3.0 and direction > 20.0  # the trap is there without the detections
    two_view = verify_two_view(query_seen, match_seen, camera, config)
    assert two_view.passed and two_view.match_from_query is not None
    rotation, direction = _errors(two_view.match_from_query, query, match)
    assert rotation < 1.0 and direction < 5.0
    boxes = [o.box for o in query_seen.objects]
    inside = [
        any(x0 <= x < x1 and y0 <= y < y1 for x0, y0, x1, y1 in boxes)
        for x, y in query.keypoints[two_view.inlier_pairs[:, 0]]
    ]
    assert not any(inside)
    # A verifier told to keep every class matches the people again.
    kept = verify_two_view(query_seen, match_seen, camera, VerifierConfig(planar_pose=True, ignore_labels=()))
    assert kept.inliers == fooled.inliers


class MissesSome:
    """The scene's walking people as a detector that misses them in the ``missed`` frames."""

    name = "misses-some"

    def __init__(self, renderer: SceneRenderer, missed: set[int]) -> None:
        self.renderer, self.missed = renderer, missed

    def detect(self, image: np.ndarray, frame: Frame | None = None) -> list[DetectedObject]:
        assert frame is not None
        if frame.index in self.missed:
            return []
        objects = self.renderer.frame(frame.index).objects
        return [DetectedObject("person", 0.9, tuple(float(v) for v in o.box)) for o in objects if o.movable]  # type: ignore[misc]


class ProposeOnce:
    """A loop detector that proposes keyframe ``match`` for keyframe ``query``."""

    name = "propose-once"
    threshold = 0.5

    def __init__(self, query: int, match: int) -> None:
        self.query, self.match = query, match

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]:
        return [LoopCandidate(keyframe.id, self.match, 10.0, {})] if keyframe.id == self.query else []


class Recording(PycolmapVerifier):
    """The pycolmap verifier, keeping the keyframes it was given."""

    def verify(self, query: Keyframe, match: Keyframe) -> Verification:
        self.given = (query, match)
        return super().verify(query, match)


MEMORY_S = LoopClosingConfig().walking_memory_s


@pytest.mark.parametrize(
    "memory_s, missed, new_segment",
    [(0.0, True, False), (MEMORY_S, True, False), (MEMORY_S, False, False), (MEMORY_S, True, True)],
)
def test_people_seen_by_neighbouring_keyframes_are_left_out(
    renderer: SceneRenderer, memory_s: float, missed: bool, new_segment: bool
) -> None:
    """The detector missed the person in both keyframes of the loop, but saw them in the keyframes
    8 frames (0.27 s) before and after each: loop closing hands those boxes to the verifier. Where
    it saw the person itself, its own box is all. ``new_segment``: the query is the first keyframe
    of a new map segment and nothing follows it; the previous segment's last keyframe saw the person."""
    query_frame, match_frame = PAIRS[1]
    after = (8,) if not new_segment else ()
    frames = [match_frame + d for d in (-8, 0, 8)] + [query_frame + d for d in (-8, 0, *after)]
    intrinsics = SynthConfig().intrinsics
    verifier = Recording(intrinsics, VerifierConfig(planar_pose=True))
    closing = LoopClosing(
        GtsamPoseGraph(BackendConfig()),
        ProposeOnce(4, 1),  # type: ignore[arg-type]
        MissesSome(renderer, {query_frame, match_frame} if missed else set()),  # type: ignore[arg-type]
        verifier,
        LoopClosingConfig(settle_keyframes=1, walking_memory_s=memory_s),
    )
    for kf_id, frame in enumerate(frames):
        rendered = renderer.frame(frame)
        features = detect_orb(cv2.cvtColor(rendered.image, cv2.COLOR_BGR2GRAY))
        pose, image = rendered.pose.copy(), rendered.image
        segment = int(new_segment and kf_id == 4)
        keyframe = Keyframe(
            kf_id, frame, rendered.timestamp, pose, features.keypoints, features.descriptors, image=image,
            segment=segment,
        )  # fmt: skip
        closing.movable_boxes(Frame(frame, rendered.timestamp, rendered.image))  # as mono-vo asks
        closing.add(TrackResult(frame, rendered.timestamp, "tracking", pose, segment, keyframe))
    closing.finish()
    query, match = verifier.given
    assert (query.frame_index, match.frame_index) == (query_frame, match_frame)
    two_view = verify_two_view(query, match, colmap_camera(intrinsics), VerifierConfig(planar_pose=True))
    assert two_view.passed and two_view.match_from_query is not None
    rotation, direction = _errors(two_view.match_from_query, query, match)
    if not missed:
        assert len(query.objects) == len(match.objects) == 1
        assert rotation < 1.0 and direction < 5.0
    elif memory_s == 0:  # the keyframes' own detections only: none
        assert not query.objects and not match.objects
        assert rotation > 3.0 and direction > 20.0
    else:  # the query's are those of the keyframes before it and of the one after (not settled yet)
        assert len(query.objects) == (1 if new_segment else 2) and len(match.objects) == 2
        assert rotation < 1.0 and direction < 5.0


def test_a_negative_walking_memory_is_a_config_error() -> None:
    from frontends.errors import ConfigError

    with pytest.raises(ConfigError, match="walking_memory_s"):
        LoopClosingConfig(walking_memory_s=-0.5)
