"""Geometric verification: true revisits give the right Sim(3), wrong pairs are rejected with a reason."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from eval.synth_keyframes import keyframe_with_depth, scene_camera
from frontends.errors import ConfigError
from frontends.synth.render import SceneRenderer
from frontends.synth.world import SynthConfig
from frontends.types import Keyframe
from slam_backend.verify import VERIFIERS, Verifier, create, match_descriptors


@pytest.fixture(scope="module")
def renderer() -> SceneRenderer:
    return SceneRenderer(SynthConfig(seed=3, trajectory="loop", frames=900))


@pytest.fixture(scope="module")
def verifier(renderer: SceneRenderer) -> Verifier:
    return VERIFIERS.load("pycolmap")(scene_camera(renderer))


def _rotation_angle_deg(r: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))


def test_revisit_gives_the_ground_truth_relative_pose(renderer: SceneRenderer, verifier: Verifier) -> None:
    match, query = keyframe_with_depth(renderer, 6, 0), keyframe_with_depth(renderer, 630, 1)
    result = verifier.verify(query, match)
    assert result.verified and result.reason == "" and result.inliers >= 100
    assert result.relative is not None and result.covariance is not None
    truth = np.linalg.inv(match.pose) @ query.pose  # metric GT on both sides: scale 1
    assert result.scale == pytest.approx(1.0, abs=0.05)
    rotation = result.relative[:3, :3] / result.scale
    assert _rotation_angle_deg(rotation.T @ truth[:3, :3]) < 0.5
    assert np.linalg.norm(result.relative[:3, 3] - truth[:3, 3]) < 0.03
    assert result.covariance.shape == (7, 7) and np.all(np.linalg.eigvalsh(result.covariance) > 0)


def test_scale_of_a_rescaled_map_is_recovered(renderer: SceneRenderer, verifier: Verifier) -> None:
    """Monocular maps have arbitrary scales: the Sim(3) carries the ratio between them."""
    match, query = keyframe_with_depth(renderer, 6, 0), keyframe_with_depth(renderer, 630, 1)
    assert query.points3d is not None
    shrunk = dataclasses.replace(query, points3d=query.points3d * 0.5)
    result = verifier.verify(shrunk, match)
    assert result.verified and result.scale == pytest.approx(
        2.0 * verifier.verify(query, match).scale, rel=1e-3
    )


def test_different_places_are_rejected_with_a_reason(renderer: SceneRenderer, verifier: Verifier) -> None:
    match, elsewhere = keyframe_with_depth(renderer, 6, 0), keyframe_with_depth(renderer, 300, 1)
    result = verifier.verify(elsewhere, match)
    assert not result.verified and result.relative is None and result.reason


def test_degenerate_keyframes(renderer: SceneRenderer, verifier: Verifier) -> None:
    match, query = keyframe_with_depth(renderer, 6, 0), keyframe_with_depth(renderer, 630, 1)
    no_map = verifier.verify(dataclasses.replace(query, points3d=None), match)
    assert not no_map.verified and "scale is unobservable" in no_map.reason
    empty = Keyframe(2, 2, 0.0, np.eye(4))
    assert "descriptor matches" in verifier.verify(empty, match).reason
    assert query.points3d is not None
    no_depth = dataclasses.replace(query, points3d=np.full_like(query.points3d, np.nan))
    assert "with map points" in verifier.verify(no_depth, match).reason


def test_matching_is_mutual_and_config_is_validated(renderer: SceneRenderer) -> None:
    keyframe = keyframe_with_depth(renderer, 6, 0)
    pairs = match_descriptors(keyframe.descriptors, keyframe.descriptors, 0.8, 80)
    assert len(pairs) > 0.9 * len(keyframe.descriptors) and np.all(pairs[:, 0] == pairs[:, 1])
    with pytest.raises(ConfigError, match="ratio"):
        create(scene_camera(renderer), ["ratio=1.5"])
    assert "pycolmap" in VERIFIERS.names()


def test_deterministic(renderer: SceneRenderer) -> None:
    match, query = keyframe_with_depth(renderer, 6, 0), keyframe_with_depth(renderer, 630, 1)
    a = create(scene_camera(renderer), ["seed=5"]).verify(query, match)
    b = create(scene_camera(renderer), ["seed=5"]).verify(query, match)
    assert a.relative is not None and b.relative is not None
    np.testing.assert_array_equal(a.relative, b.relative)
