"""Synthetic scenes: determinism, TUM layout, ground-truth geometry, loops, texture quality, CLI."""

from __future__ import annotations

import argparse
import hashlib
import json
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from frontends.config import load_config
from frontends.errors import ConfigError
from frontends.gt_loops import read_loop_pairs
from frontends.synth import SceneRenderer, SynthConfig, cached_scene, render_frames, write_scene
from frontends.synth import cli as synth_cli
from frontends.synth.covisibility import label_covisible_pairs, overlap_matrix
from frontends.synth.trajectories import camera_path
from frontends.trajectory_io import read_tum

#: A quarter-size camera (same field of view) keeps the disk-writing tests fast.
SMALL = {"width": 320, "height": 240, "fx": 262.5, "fy": 262.5, "cx": 159.5, "cy": 119.5}


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
    out = tmp_path_factory.mktemp("synth") / "scene"
    write_scene(small_config(frames=40, seed=5), out, progress=False, contact_sheet=out.parent / "sheet.png")
    return out


@pytest.fixture(scope="module")
def full_scene() -> SceneRenderer:
    return SceneRenderer(SynthConfig(frames=150, seed=2))


def test_same_seed_gives_byte_identical_files(scene_dir: Path, tmp_path: Path) -> None:
    write_scene(small_config(frames=40, seed=5), tmp_path / "again", progress=False)
    first, second = file_hashes(scene_dir), file_hashes(tmp_path / "again")
    assert len(first) == 40 + 6
    assert first == second


def test_different_seed_gives_different_images() -> None:
    frames = [next(render_frames(small_config(frames=2, seed=seed)))[1] for seed in (0, 1)]
    assert np.abs(frames[0].astype(int) - frames[1]).mean() > 10


def test_tum_layout_parses(scene_dir: Path) -> None:
    rows = [
        line.split() for line in (scene_dir / "rgb.txt").read_text().splitlines() if not line.startswith("#")
    ]
    assert len(rows) == 40
    assert rows[1] == ["1.033333", "rgb/1.033333.png"]
    assert all((scene_dir / name).is_file() for _, name in rows)
    image = cv2.imread(str(scene_dir / rows[0][1]))
    assert image is not None and image.shape == (240, 320, 3)
    trajectory = read_tum(scene_dir / "groundtruth.txt")
    assert trajectory.num_poses == 40
    np.testing.assert_allclose(trajectory.timestamps, [float(stamp) for stamp, _ in rows])
    intrinsics = yaml.safe_load((scene_dir / "intrinsics.yaml").read_text())
    assert intrinsics == {**SMALL, "distortion": []}
    lines = [json.loads(line) for line in (scene_dir / "gt_objects.jsonl").read_text().splitlines()]
    assert [line["frame"] for line in lines] == list(range(40))
    for obj in (o for line in lines for o in line["objects"]):
        assert set(obj) == {"label", "instance", "box", "visible_fraction", "movable"}
        x0, y0, x1, y1 = obj["box"]
        assert 0 <= x0 < x1 <= 320 and 0 <= y0 < y1 <= 240
        assert 0 < obj["visible_fraction"] <= 1
    assert (scene_dir / "gt_loop_pairs.txt").read_text().startswith("# query ref")
    pairs = read_loop_pairs(scene_dir / "gt_loop_pairs.txt", 40)
    assert ((pairs[:, 1] < pairs[:, 0]) & (pairs[:, 1] >= 0)).all()
    scene = json.loads((scene_dir / "scene.json").read_text())
    assert scene["loop_labels"]["min_overlap"] == SynthConfig().loop_labels.min_overlap
    assert (scene_dir.parent / "sheet.png").is_file()


def test_world_has_repeated_static_classes_and_movable_people(scene_dir: Path) -> None:
    objects = json.loads((scene_dir / "scene.json").read_text())["objects"]
    static = [o["label"] for o in objects if not o["movable"]]
    assert len(static) >= 8
    assert max(Counter(static).values()) >= 2
    assert [o["label"] for o in objects if o["movable"]] == ["person", "person"]


def test_movable_objects_move_and_are_flagged(full_scene: SceneRenderer) -> None:
    people = [obj for obj in full_scene.world.objects if obj.movable]
    assert people and all(obj.label == "person" for obj in people)
    for obj in people:
        assert np.linalg.norm(obj.centre_at(1.0) - obj.centre_at(3.0)) > 0.1
    seen = [o for i in range(0, 150, 10) for o in full_scene.frame(i).objects]
    assert any(o.label == "person" for o in seen)
    assert all(o.movable == (o.label == "person") for o in seen)


@pytest.mark.parametrize(
    ("kind", "has_loops"),
    [
        ("loop", True),
        pytest.param("figure8", True, marks=pytest.mark.slow),
        pytest.param("out-and-back", True, marks=pytest.mark.slow),
        pytest.param("none", False, marks=pytest.mark.slow),
    ],
)
def test_ground_truth_loops_by_trajectory(kind: str, has_loops: bool) -> None:
    config = small_config(trajectory=kind, frames=300)
    scene = SceneRenderer(config)
    grids = []
    for index in range(config.frames):
        scene.frame(index)
        grids.append(scene.depth_samples(config.loop_labels.depth_step))
    overlap = overlap_matrix(np.stack(grids), scene.path.poses, config.intrinsics, config.loop_labels)
    pairs = label_covisible_pairs(overlap, scene.path.poses, scene.path.timestamps, config.loop_labels)
    assert (len(pairs) > 0) == has_loops
    if has_loops:
        # Revisits come from the second pass, not from neighbouring frames of one pass.
        gaps = scene.path.timestamps[pairs[:, 0]] - scene.path.timestamps[pairs[:, 1]]
        assert gaps.min() >= config.loop_labels.min_time_gap


@pytest.mark.parametrize("kind", ["loop", "figure8", "out-and-back", "none"])
@pytest.mark.parametrize("frames", [300, 600])
def test_camera_motion_is_trackable_and_inside_the_room(kind: str, frames: int) -> None:
    config = SynthConfig(trajectory=kind, frames=frames)  # type: ignore[arg-type]
    path = camera_path(config)
    assert 0.3 <= path.mean_speed <= 1.0
    assert path.max_rotation_deg < 3.0
    half = np.array(config.room_size[:2]) / 2
    assert (np.abs(path.poses[:, :2, 3]) < half - 1.5).all()
    assert np.allclose(path.poses[:, 3], [0, 0, 0, 1])


def test_boxes_agree_with_projected_cuboids(full_scene: SceneRenderer) -> None:
    config = full_scene.config
    checked = 0
    for index in range(0, 150, 3):
        frame = full_scene.frame(index)
        world_to_camera = np.linalg.inv(frame.pose)
        for obj in frame.objects:
            x0, y0, x1, y1 = obj.box
            inside = x0 > 0 and y0 > 0 and x1 < config.width and y1 < config.height
            if obj.visible_fraction < 0.999 or not inside:
                continue
            corners = full_scene.world.objects[obj.instance - 1].corners_at(frame.timestamp)
            camera = corners @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
            uv = camera @ config.intrinsics.K.T
            uv = uv[:, :2] / uv[:, 2:]
            projected = [uv[:, 0].min(), uv[:, 1].min(), uv[:, 0].max() + 1, uv[:, 1].max() + 1]
            np.testing.assert_allclose(projected, obj.box, atol=2.0)
            checked += 1
    assert checked >= 3


def test_frames_have_plenty_of_orb_features(full_scene: SceneRenderer) -> None:
    orb = cv2.ORB.create(1000)
    for index in (0, 75, 149):
        gray = cv2.cvtColor(full_scene.frame(index).image, cv2.COLOR_BGR2GRAY)
        assert len(orb.detect(gray, None)) > 500


def test_invalid_config_and_foreign_output_folder_are_rejected(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="frames"):
        SynthConfig(frames=1)
    with pytest.raises(ConfigError, match="room_size"):
        SynthConfig(room_size=(4.0, 4.0, 2.5))
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError, match="not empty"):
        write_scene(small_config(frames=2), tmp_path, progress=False)


def test_synth_parser_registers_its_handler(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    synth_cli.add_parser(parser.add_subparsers())
    args = parser.parse_args(
        ["synth", "--frames", "5", "--out", str(tmp_path), "--set", "frames=9", "--set", "noise_sigma=3"]
    )
    assert args.handler is synth_cli.run
    assert args.frames == 5 and args.overrides == ["frames=9", "noise_sigma=3"]


def test_cli_writes_a_scene(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from eval.cli import main

    # --set frames=99 loses against the explicit --frames flag.
    settings = [
        item for key, value in {**SMALL, "frames": 99}.items() for item in ("--set", f"{key}={value}")
    ]
    code = main(
        [
            "synth",
            "--trajectory",
            "none",
            "--seed",
            "4",
            "--frames",
            "12",
            "--out",
            str(tmp_path / "s"),
            "--no-progress",
            "--json",
            str(tmp_path / "figures.json"),
            *settings,
        ]
    )
    assert code == 0
    figures = json.loads((tmp_path / "figures.json").read_text())
    assert figures["frames"] == 12 and figures["gt_loop_pairs"] == 0 and figures["render_fps"] > 0
    assert "gt_loop_pairs" in capsys.readouterr().out
    assert json.loads((tmp_path / "s" / "scene.json").read_text())["config"]["seed"] == 4


def test_cached_scene_is_reused_only_for_the_same_config(tmp_path: Path) -> None:
    folder = tmp_path / "scene"
    cached_scene(small_config(frames=4, seed=1), folder)
    written = (folder / "scene.json").stat().st_mtime_ns
    cached_scene(small_config(frames=4, seed=1), folder)
    assert (folder / "scene.json").stat().st_mtime_ns == written
    # A changed labeller (or any other setting) re-renders: stale GT loops are never reused.
    cached_scene(small_config(frames=4, seed=1, **{"loop_labels.min_overlap": 0.6}), folder)
    assert json.loads((folder / "scene.json").read_text())["loop_labels"]["min_overlap"] == 0.6
