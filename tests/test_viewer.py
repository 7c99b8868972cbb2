"""The optional rerun viewer: a short synthetic run records a complete, readable .rrd.

The recording test skips itself where the ``viewer`` extra (rerun-sdk) is not installed; the
others need no rerun (the missing-extra error is what such an install must show).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from frontends.base import TrackResult
from frontends.errors import ConfigError
from frontends.orb import OrbConfig, extract_orb
from frontends.synth.render import SceneRenderer
from frontends.synth.world import SynthConfig
from frontends.types import CameraIntrinsics, DetectedObject, Frame, Keyframe
from lcd.graph import AROUND, DISTANCE, INSIDE, GraphConfig, build_graph
from lcd.objects.filtering import filter_objects
from slam_backend.pipeline import LoopRecord

CONFIG = SynthConfig(width=320, height=240, fx=262.5, fy=262.5, cx=159.5, cy=119.5, frames=60)
CAMERA = CameraIntrinsics(262.5, 262.5, 159.5, 119.5, 320, 240)
FRAMES = 10
KEYFRAMES = (0, 4, 8)

EXPECTED_ENTITIES = {
    "/world",
    "/world/camera",
    "/world/camera/image",
    "/world/trajectory/odometry",
    "/world/trajectory/final",
    "/world/trajectory/final_odometry",
    "/world/keyframes",
    "/world/loops/accepted",
    "/world/loops/rejected",
    "/keyframe/image",
    "/keyframe/keypoints",
    "/keyframe/objects",
    "/keyframe/graph/tier1",
    "/keyframe/graph/tier2",
    "/keyframe/graph/tier3",
}


def test_missing_rerun_is_a_config_error(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from eval.viewer import RerunViewer

    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(ConfigError, match=r"symbiolcd2\[viewer\]"):
        RerunViewer(tmp_path / "run.rrd")


def _keyframe(renderer: SceneRenderer, index: int, keyframe_id: int) -> Keyframe:
    rendered = renderer.frame(index)
    gray = rendered.image.mean(axis=2).astype(np.uint8)
    keypoints, descriptors = extract_orb(gray, OrbConfig())
    objects = tuple(
        DetectedObject(o.label, 1.0, (o.box[0], o.box[1], o.box[2], o.box[3]), instance=o.instance)
        for o in rendered.objects
    )
    return Keyframe(
        id=keyframe_id,
        frame_index=index,
        timestamp=rendered.timestamp,
        pose=rendered.pose,
        keypoints=keypoints,
        descriptors=descriptors,
        objects=objects,
        image=rendered.image,
    )


def test_run_records_a_complete_rrd(tmp_path: Path) -> None:
    rr = pytest.importorskip("rerun")
    from eval.viewer import RerunViewer, graph_segments

    renderer = SceneRenderer(CONFIG)
    rrd = tmp_path / "out" / "run.rrd"
    viewer = RerunViewer(rrd, camera=CAMERA, trajectory_every=4)
    keyframes: list[Keyframe] = []
    poses: list[tuple[int, float, np.ndarray]] = []
    feature_edges = 0
    for index in range(FRAMES):
        timestamp = float(renderer.path.timestamps[index])
        pose = renderer.path.poses[index]
        frame = Frame(index, timestamp, np.zeros((2, 2), np.uint8))
        keyframe = _keyframe(renderer, index, len(keyframes)) if index in KEYFRAMES else None
        viewer.frame(frame, TrackResult(index, timestamp, "tracking", pose, keyframe=keyframe))
        poses.append((index, timestamp, pose))
        if keyframe is not None:
            keyframes.append(keyframe)
            kept = filter_objects(keyframe.objects, (CONFIG.width, CONFIG.height))
            words = np.zeros(len(keyframe.keypoints), dtype=np.int64)
            graph = build_graph(keyframe.keypoints, words, kept, GraphConfig())
            tiers = {t: len(s) for t, s in graph_segments(keyframe, graph).items()}
            # The layout reproduced the graph: its own edges are drawn, the object-object ones
            # through their distance node (two segments per pair; the geometric fallback draws one).
            kinds = graph.kinds
            assert len(kept) >= 2
            assert tiers == {
                1: 2 * int((kinds == DISTANCE).sum()),
                2: int((kinds == INSIDE).sum()),
                3: int((kinds == AROUND).sum()),
            }
            feature_edges += tiers[2] + tiers[3]
            viewer.keyframe(keyframe, graph)
    assert feature_edges > 0
    first, _, last = keyframes
    for accepted in (True, False):
        record = LoopRecord(
            query=last.id,
            match=first.id if accepted else 1,
            query_frame=last.frame_index,
            match_frame=(first if accepted else keyframes[1]).frame_index,
            score=0.8,
            verified=True,
            inliers=40 if accepted else 5,
            accepted=accepted,
            reason="" if accepted else "too few inliers",
        )
        viewer.loop(record, last.pose, first.pose if accepted else keyframes[1].pose)
    viewer.trajectories(poses, poses)
    viewer.close()

    assert rrd.is_file()
    assert rrd.stat().st_size > 50_000  # three keyframe images at least
    reader_module = getattr(rr, "chunk", None)
    if reader_module is None or not hasattr(reader_module, "RrdReader"):
        pytest.skip(f"rerun {rr.__version__} cannot read recordings back")
    schema = reader_module.RrdReader(rrd).store().schema()
    entities = {str(e) for e in schema.entity_paths()}
    assert entities >= EXPECTED_ENTITIES, EXPECTED_ENTITIES - entities


def test_graph_edges_fall_back_to_geometry() -> None:
    from eval.viewer import geometric_segments, graph_segments

    keypoints = np.array([[15.0, 15.0], [40.0, 15.0], [90.0, 90.0], [200.0, 200.0]], dtype=np.float32)
    objects = (
        DetectedObject("cup", 0.9, (10.0, 10.0, 20.0, 20.0)),
        DetectedObject("book", 0.9, (80.0, 80.0, 100.0, 100.0)),
    )
    keyframe = Keyframe(0, 0, 0.0, np.eye(4), keypoints=keypoints, objects=objects)
    tiers = geometric_segments(keypoints, objects)
    assert [len(tiers[t]) for t in (1, 2, 3)] == [1, 2, 1]  # cup-book; inside each; (40, 15) near the cup
    # A graph built with a wider margin than the viewer assumes: its layout is not reproduced.
    graph = build_graph(keypoints, np.zeros(4, np.int64), objects, GraphConfig(margin_px=200.0))
    drawn = graph_segments(keyframe, graph)
    assert {t: len(s) for t, s in drawn.items()} == {1: 1, 2: 2, 3: 1}
