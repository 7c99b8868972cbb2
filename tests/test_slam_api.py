"""``slam_backend.Slam``: the system a user imports, and the one ``symbio run`` runs."""

from __future__ import annotations

import itertools
import json
import re
from pathlib import Path

import numpy as np
import pytest

from eval.cli import main as symbio_main
from eval.run import TRAJECTORY_FILE
from frontends.datasets import open_dataset
from frontends.trajectory_io import read_tum
from frontends.types import Keyframe
from lcd.base import LOOP_DETECTORS, LoopCandidate
from slam_backend import Slam, SlamResult
from slam_backend.slam import RESULT_FILES


class RecordingDetector:
    """A loop detector object of the user's: vbow underneath, recording what it was given."""

    name = "recording"

    def __init__(self) -> None:
        self.inner = LOOP_DETECTORS.load("vbow")([])
        self.threshold = self.inner.threshold
        self.seen: list[Keyframe] = []

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]:
        self.seen.append(keyframe)
        return self.inner.add(keyframe)


def test_a_detector_object_gets_every_keyframe_with_its_objects(
    small_loop_scene: Path, tmp_path: Path
) -> None:
    dataset = open_dataset(small_loop_scene)
    detector = RecordingDetector()
    slam = Slam(dataset.camera, loop_detector=detector, object_detector="oracle")
    for frame in itertools.islice(dataset, 150):
        slam.track(frame)
    result = slam.finish()
    assert isinstance(result, SlamResult)
    assert result.figures["detector"] == "recording" and result.figures["frames"] == 150
    assert len(detector.seen) == len(result.keyframes) > 5
    assert [k.id for k in detector.seen] == [k.id for k in result.keyframes]
    assert any(k.objects for k in detector.seen)  # the oracle's boxes reached the detector
    assert len(result.trajectory) == result.figures["frames_tracked"] >= 140
    assert set(result.keyframe_poses) == {k.id for k in result.keyframes}
    paths = result.save(tmp_path / "out")
    assert [p.name for p in paths] == list(RESULT_FILES)
    assert read_tum(paths[0]).num_poses == len(result.trajectory)
    assert json.loads(paths[-1].read_text())["keyframes"] == len(result.keyframes)
    again = slam.finish()  # finishing twice changes nothing
    assert again.loops == result.loops and again.figures["keyframes"] == result.figures["keyframes"]
    np.testing.assert_array_equal(
        np.array([p for _, _, p in again.trajectory]), np.array([p for _, _, p in result.trajectory])
    )
    with pytest.raises(RuntimeError, match="after finish"):
        slam.track(next(iter(dataset)))


def test_odometry_only_and_bad_arguments(small_loop_scene: Path) -> None:
    dataset = open_dataset(small_loop_scene)
    slam = Slam(dataset.camera, loop_detector=None, object_detector="no-such-detector")
    assert slam.closing.detector is None and slam.closing.objects is None  # nothing else is loaded
    with pytest.raises(RuntimeError, match="before finish"):
        slam.result()
    result = slam.run(itertools.islice(dataset, 60))
    assert result.figures["loop_closing"] is False and result.loops == []
    odometry = np.array([p for _, _, p in result.odometry])
    corrected = np.array([p for _, _, p in result.trajectory])
    np.testing.assert_allclose(corrected, odometry, atol=1e-9)
    with pytest.raises(ValueError, match="unknown part"):
        Slam(dataset.camera, loop_detector=None, overrides={"detectr": ["x=1"]})
    with pytest.raises(Exception, match="no-such"):
        Slam(dataset.camera, object_detector="no-such")


@pytest.mark.slow
def test_the_api_is_what_symbio_run_runs(small_loop_scene: Path, tmp_path: Path) -> None:
    """Frame by frame through ``Slam.track`` gives the trajectory ``symbio run`` writes, loops and all."""
    out = tmp_path / "cli"
    assert symbio_main(["run", str(small_loop_scene), "--out", str(out), "--no-progress"]) == 0
    cli = read_tum(out / TRAJECTORY_FILE)
    dataset = open_dataset(small_loop_scene)
    slam = Slam(dataset.camera, object_detector="oracle")
    for frame in dataset:
        slam.track(frame)
    result = slam.finish()
    assert result.figures["loops_accepted"] > 0
    assert len(result.trajectory) == cli.num_poses
    np.testing.assert_allclose(
        np.array([p for _, _, p in result.trajectory]), np.array(cli.poses_se3), atol=1e-6
    )


@pytest.mark.slow
def test_the_readme_python_quick_start_runs(small_loop_scene: Path, tmp_path: Path) -> None:
    readme = (Path(__file__).resolve().parent.parent / "README.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```python\n(.*?)```", readme, re.DOTALL)
    assert len(blocks) == 1, "the README's Python quick start"
    code = (
        blocks[0]
        .replace('"scene"', repr(str(small_loop_scene)))
        .replace('"out"', repr(str(tmp_path / "out")))
    )
    namespace: dict[str, object] = {}
    exec(compile(code, "README.md", "exec"), namespace)  # the project's own README, not user data
    result = namespace["result"]
    assert isinstance(result, SlamResult) and result.figures["frames_tracked"] >= 590
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(RESULT_FILES)


def test_the_run_state_keeps_no_point_observations() -> None:
    """``SlamState`` keeps every frame's result for the whole run without the point observations
    (loop closing keeps its own compact copy for re-posing): ~14 kB per frame otherwise. A result
    posed late replaces the earlier one, also without them."""
    from frontends.base import PointObservations, TrackResult
    from slam_backend.slam import SlamState

    observations = PointObservations(np.zeros((500, 2)), np.arange(500))
    state = SlamState()
    state.add(TrackResult(0, 0.0, "initialising", None))
    late = TrackResult(0, 0.0, "tracking", np.eye(4), observations=observations)
    state.add(TrackResult(1, 0.1, "tracking", np.eye(4), observations=observations, backfilled=(late,)))
    assert [r.frame_index for r in state.results] == [0, 1]
    assert [r.state for r in state.results] == ["tracking", "tracking"]
    assert all(r.observations is None and r.backfilled == () for r in state.results)
    assert all(r.pose is not None for r in state.results)
