"""The bays layout: identical textures from bay to bay, different objects, object-rich views, and a
hall path whose revisits (same and opposite direction) the covisibility labeller finds."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from frontends.config import load_config
from frontends.errors import ConfigError
from frontends.gt_loops import read_loop_pairs
from frontends.synth import SceneRenderer, SynthConfig, write_scene
from frontends.synth.render import Rasteriser, _Face, _normal
from frontends.synth.trajectories import HALL_END_CLEARANCE, camera_path
from frontends.synth.world import bay_of, build_world, hall_size

#: A 160x120 camera (same field of view as 640x480), 5 fps: 150 frames walk 21 m, the first three
#: legs of the hall path (east, west, east again), at the default speed.
SMALL = {
    "layout": "bays",
    "trajectory": "hall",
    "width": 160,
    "height": 120,
    "fx": 131.25,
    "fy": 131.25,
    "cx": 79.5,
    "cy": 59.5,
    "fps": 5.0,
    "frames": 150,
    "wall_texels_per_m": 150.0,
    "object_texels_per_m": 150.0,
    "loop_labels.depth_step": 4,
    "loop_labels.sample_every": 2,
}


def small_config(**changes: object) -> SynthConfig:
    return load_config(SynthConfig, None, [f"{k}={v}" for k, v in {**SMALL, **changes}.items()])


def file_hashes(root: Path) -> dict[str, str]:
    return {
        str(path.relative_to(root)): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(root.rglob("*"))
        if path.is_file()
    }


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from eval.cli import main

    out = tmp_path_factory.mktemp("alias") / "scene"
    settings = [item for key, value in SMALL.items() for item in ("--set", f"{key}={value}")]
    figures = out.parent / "figures.json"
    code = main(["synth", *settings, "--out", str(out), "--no-progress", "--json", str(figures)])
    assert code == 0
    assert json.loads(figures.read_text())["objects_per_frame_mean"] > 0
    return out


def test_bays_repeat_identical_textures() -> None:
    config = small_config()
    world = build_world(config)
    length, width, height = config.bay_size
    assert world.room_size == hall_size(config) == (3 * length, width, height)
    # North wall, south wall, floor, ceiling of each bay, then the two end walls.
    assert len(world.room) == 4 * config.bays + 2
    for kind in range(4):
        first = world.room[kind]
        for bay in range(1, config.bays):
            other = world.room[4 * bay + kind]
            assert all(np.array_equal(a, b) for a, b in zip(first.pyramid, other.pyramid, strict=True))
            np.testing.assert_allclose(other.corners - first.corners, [[bay * length, 0, 0]] * 4, atol=1e-9)
    assert not np.array_equal(world.room[0].pyramid[0], world.room[1].pyramid[0])


def _room_only_image(config: SynthConfig, x: float) -> np.ndarray:
    """The bare hall (no objects) seen from (x, 0) at eye height, looking north."""
    world = build_world(config)
    raster = Rasteriser(config)
    pose = np.eye(4)
    # Camera x right (east), y down, z forward (north).
    pose[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]
    pose[:3, 3] = [x, 0.0, config.camera_height]
    world_to_camera = np.linalg.inv(pose)
    for surface in world.room:
        raster.draw(_Face(surface.corners, _normal(surface.corners), surface, 0), world_to_camera)
    return raster.image.astype(np.int16)


def test_rendered_bays_look_the_same_one_bay_apart() -> None:
    # A narrower field of view: the bare walls of the middle bays fill the image.
    config = small_config(fx=200.0, fy=200.0)
    length = config.bay_size[0]
    first, next_bay, half_bay = (_room_only_image(config, x) for x in (-length, 0.0, -length / 2))
    # One bay along, the same wall texture in the same place of the image; half a bay, another one.
    assert np.abs(first - next_bay).mean() < 1.0
    assert np.abs(first - half_bay).mean() > 15.0


def test_bays_hold_different_object_arrangements() -> None:
    config = small_config()
    world = build_world(config)
    length = config.bay_size[0]
    arrangements = []
    for bay in range(config.bays):
        west = -config.bays * length / 2 + bay * length
        arrangements.append(
            sorted(
                (obj.label, obj.centre[1] > 0, round(obj.centre[0] - west, 1))
                for obj in world.objects
                if not obj.movable and bay_of(config, obj.centre[0]) == bay
            )
        )
    assert all(len(arrangement) >= 8 for arrangement in arrangements)
    for a in range(config.bays):
        for b in range(a + 1, config.bays):
            assert arrangements[a] != arrangements[b]
            labels = [sorted(label for label, _, _ in arrangements[k]) for k in (a, b)]
            assert labels[0] != labels[1]


def test_default_bays_scene_is_object_rich() -> None:
    config = SynthConfig(layout="bays", trajectory="hall", frames=900)
    scene = SceneRenderer(config)
    counts = [sum(not obj.movable for obj in scene.frame(i).objects) for i in range(0, 900, 30)]
    assert np.mean(counts) >= 6


def test_hall_path_is_trackable_and_inside_the_hall() -> None:
    for frames in (300, 900, 2000):
        config = SynthConfig(layout="bays", trajectory="hall", frames=frames)
        path = camera_path(config)
        assert 0.6 <= path.mean_speed <= 0.8
        assert path.max_rotation_deg < 3.0
        length, width, _ = hall_size(config)
        assert (np.abs(path.poses[:, 0, 3]) < length / 2 - HALL_END_CLEARANCE + 0.6).all()
        assert (np.abs(path.poses[:, 1, 3]) < width / 2 - 2.0).all()
        # The walking people keep clear of the camera (they cross the hall beyond its turns).
        people = [obj for obj in build_world(config).objects if obj.movable]
        assert len(people) == config.movable_objects
        for obj in people:
            where = np.array([obj.centre_at(float(t))[:2] for t in path.timestamps])
            assert np.linalg.norm(where - path.poses[:, :2, 3], axis=1).min() > 0.5


def _travel(config: SynthConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame: camera centre, sign of the motion along the hall, yaw of the optical axis (deg)."""
    path = camera_path(config)
    centres = path.poses[:, :3, 3]
    axis = path.poses[:, :3, 2]
    return centres, np.sign(np.gradient(centres[:, 0])), np.degrees(np.arctan2(axis[:, 1], axis[:, 0]))


def test_ground_truth_loops_include_opposite_direction_revisits(scene_dir: Path) -> None:
    config = small_config()
    pairs = read_loop_pairs(scene_dir / "gt_loop_pairs.txt", config.frames)
    centres, direction, yaw = _travel(config)
    query, ref = pairs[:, 0], pairs[:, 1]
    opposite = direction[query] != direction[ref]
    assert opposite.sum() >= 20 and (~opposite).sum() >= 20
    turn = np.abs((yaw[query] - yaw[ref] + 180) % 360 - 180)
    assert turn[opposite].mean() > 25.0 and turn[~opposite].mean() < 15.0
    gaps = (query - ref) / config.fps
    assert gaps.min() >= config.loop_labels.min_time_gap
    # Has-been-away: the way to the east end and straight back does not label the end's views.
    east_turn = hall_size(config)[0] / 2 - HALL_END_CLEARANCE
    first_leg = np.flatnonzero(direction < 0)[0]
    near_end = (ref < first_leg) & (centres[ref, 0] > east_turn - 1.0) & (query < 2 * first_leg)
    assert not near_end.any()


def test_same_config_gives_byte_identical_files(scene_dir: Path, tmp_path: Path) -> None:
    write_scene(small_config(), tmp_path / "again", progress=False)
    first, second = file_hashes(scene_dir), file_hashes(tmp_path / "again")
    assert len(first) == 150 + 6
    assert first == second
    assert json.loads((scene_dir / "scene.json").read_text())["config"]["layout"] == "bays"


@pytest.mark.parametrize(
    ("override", "field"),
    [
        ("bays=1", "bays"),
        ("bays=40", "bays"),
        ("bay_size=[2.0, 6.0, 2.8]", "bay_size"),
        ("bay_size=[3.5, 3.0, 2.8]", "bay_size"),
        ("layout=hallway", "layout"),
    ],
)
def test_bad_bays_values_are_rejected(override: str, field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        load_config(SynthConfig, None, ["layout=bays", "trajectory=hall", override])


def test_hall_and_bays_go_together() -> None:
    with pytest.raises(ConfigError, match="layout"):
        SynthConfig(trajectory="hall")
    with pytest.raises(ConfigError, match="trajectory hall"):
        camera_path(SynthConfig(layout="bays"))
