"""Every script in ``examples/`` runs as a user would run it and prints what it promises.

Each example runs in its own interpreter (``python examples/NAME.py``, the venv's python, from the
repository root, with a timeout); the assertions read the figures it printed and fail when the
example breaks (wrong result, exception, missing output). All examples start at once and run
concurrently; each test waits for its own.
"""

from __future__ import annotations

import ast
import math
import re
import runpy
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from evo.core import lie_algebra
from evo.core.trajectory import PoseTrajectory3D

from frontends.trajectory_io import write_trajectory
from frontends.types import Keyframe

REPO_ROOT = Path(__file__).resolve().parent.parent
EXAMPLES = REPO_ROOT / "examples"
TIMEOUT_S = 300


class Example:
    """One example started in the background (``subprocess.Popen``); ``output()`` waits for it."""

    def __init__(self, name: str, *args: str) -> None:
        self.command = [sys.executable, str(EXAMPLES / name), *args]
        self.process = subprocess.Popen(
            self.command, cwd=REPO_ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )

    def output(self) -> str:
        try:
            stdout, stderr = self.process.communicate(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.communicate()
            pytest.fail(f"{' '.join(self.command)} did not finish within {TIMEOUT_S} s")
        if self.process.returncode != 0:
            pytest.fail(f"{' '.join(self.command)} exited {self.process.returncode}:\n{stderr[-3000:]}")
        return stdout

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.communicate()


def number(pattern: str, text: str) -> float:
    """The number captured by ``pattern`` in an example's output (fails the test when absent)."""
    found = re.search(pattern, text, re.MULTILINE)
    assert found, f"{pattern!r} not in the output:\n{text}"
    return float(found.group(1))


def textured_image(seed: int) -> np.ndarray:
    """A blurred random-blob image (plenty of ORB corners)."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    image = cv2.resize(small, (640, 480), interpolation=cv2.INTER_NEAREST)
    return cv2.GaussianBlur(image, (0, 0), 1.0)


def tum_pair(folder: Path) -> tuple[Path, Path]:
    """A ground-truth circle and the same path at half the scale in another frame (scale 2 to recover)."""
    times = np.arange(100) / 10.0
    angles = np.linspace(0.0, 1.5 * math.pi, len(times))
    gt = [
        lie_algebra.se3(
            lie_algebra.so3_exp(np.array([0.0, 0.0, a + math.pi / 2])),
            np.array([math.cos(a), math.sin(a), 0.1 * a]),
        )
        for a in angles
    ]
    frame = lie_algebra.se3(lie_algebra.so3_exp(np.array([0.2, -0.1, 0.7])), np.array([1.0, 2.0, 3.0]))
    estimate = []
    for pose in gt:
        scaled = pose.copy()
        scaled[:3, 3] *= 0.5
        estimate.append(frame @ scaled)
    gt_file, estimate_file = folder / "gt.txt", folder / "estimate.txt"
    write_trajectory(gt_file, PoseTrajectory3D(poses_se3=gt, timestamps=times))
    write_trajectory(estimate_file, PoseTrajectory3D(poses_se3=estimate, timestamps=times))
    return gt_file, estimate_file


@pytest.fixture(scope="module")
def examples(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Example]]:
    """Start every example run of this module at once (they are independent processes)."""
    folder = tmp_path_factory.mktemp("examples")
    images = [folder / "a.png", folder / "b.png"]
    for path, seed in zip(images, (1, 2), strict=True):
        cv2.imwrite(str(path), textured_image(seed))
    gt_file, estimate_file = tum_pair(folder)
    runs = {
        "plugin": Example("custom_loop_detector_plugin.py"),
        "sim3": Example("sim3_pose_graph_loop.py"),
        "symbiolcd2": Example("symbiolcd2_two_images.py"),
        "symbiolcd2_paths": Example(
            "symbiolcd2_two_images.py", str(images[0]), str(images[1]), "--object-detector", "none"
        ),
        "evo": Example("evaluate_trajectory_evo.py"),
        "evo_files": Example("evaluate_trajectory_evo.py", str(gt_file), str(estimate_file)),
        "slam": Example("slam_in_python.py", "--out", str(folder / "slam_out")),
    }
    yield runs
    for run in runs.values():
        run.stop()


def test_every_example_is_tested_and_listed() -> None:
    scripts = sorted(path.name for path in EXAMPLES.glob("*.py"))
    tested = {
        "custom_loop_detector_plugin.py",
        "evaluate_trajectory_evo.py",
        "sim3_pose_graph_loop.py",
        "slam_in_python.py",
        "symbiolcd2_two_images.py",
    }
    assert set(scripts) == tested, "a new example needs a test here"
    listing = (EXAMPLES / "README.md").read_text(encoding="utf-8")
    for name in scripts:
        assert f"python examples/{name}" in listing, f"examples/README.md does not say how to run {name}"


def test_sim3_pose_graph_loop(examples: dict[str, Example]) -> None:
    out = examples["sim3"].output()
    assert re.search(r"^loop decision: accepted", out, re.MULTILINE), out
    drift_before = number(r"^end-point drift: +odometry ([\d.]+) m", out)
    drift_after = number(r"^end-point drift: .*optimised ([\d.]+) m", out)
    ape_before = number(r"^APE RMSE \(positions\): +odometry ([\d.]+) m", out)
    ape_after = number(r"^APE RMSE \(positions\): .*optimised ([\d.]+) m", out)
    assert drift_before > 1.0  # the odometry really drifts
    assert drift_after < 0.1 * drift_before
    assert ape_after < 0.2 * ape_before
    true_scale = number(r"^map scale at the end: +true ([\d.]+)", out)
    optimised_scale = number(r"^map scale at the end: .*optimised ([\d.]+)", out)
    assert optimised_scale == pytest.approx(true_scale, rel=0.05)


def graph_tiers(out: str) -> list[dict[str, int]]:
    return [
        ast.literal_eval(found) for found in re.findall(r"^  graph: .* edges, (\{.*\})$", out, re.MULTILINE)
    ]


def test_symbiolcd2_two_synthetic_views(examples: dict[str, Example]) -> None:
    out = examples["symbiolcd2"].output()
    assert "candidate: keyframe 1 revisits keyframe 0" in out
    score, wl, temporal = (number(rf"^ *{key}: (-?[\d.]+)", out) for key in ("score", "wl", "temporal"))
    assert all(math.isfinite(v) for v in (score, wl, temporal))
    assert score == pytest.approx(wl - temporal, abs=2e-4)  # printed with 4 decimals
    assert 0.0 < wl <= 1.0 and temporal > 0.0
    tiers = graph_tiers(out)
    assert len(tiers) == 2
    for sizes in tiers:  # the full three-tier graph: objects, features inside and around them
        assert sizes["scene"] == 1
        assert sizes["object"] >= 1 and sizes["tier2"] > 0 and sizes["tier3"] > 0


def test_symbiolcd2_two_image_files(examples: dict[str, Example]) -> None:
    out = examples["symbiolcd2_paths"].output()
    assert "candidate: keyframe 1 revisits keyframe 0" in out
    assert math.isfinite(number(r"^score: (-?[\d.]+)", out))
    tiers = graph_tiers(out)
    assert len(tiers) == 2
    for sizes in tiers:  # no object detector: features only, on the scene node
        assert sizes["object"] == 0 and sizes["tier0"] > 100


@pytest.mark.slow
def test_slam_in_python_with_own_detector(examples: dict[str, Example]) -> None:
    out = examples["slam"].output()
    assert "detector: my-symbiolcd2" in out  # the object passed in, not a registered one
    frames = number(r"^frames tracked: (\d+) of 600", out)
    assert frames >= 590
    assert number(r"^loops accepted: (\d+) of", out) >= 5
    assert number(r"^corrected poses: (\d+)", out) == frames
    written = re.search(r"^wrote (.*)$", out, re.MULTILINE)
    assert written, out
    paths = [Path(p) for p in written.group(1).split(", ")]
    assert [p.name for p in paths] == [
        "trajectory_tum.txt", "trajectory_odometry_tum.txt", "keyframes_tum.txt", "loops.csv", "figures.json",
    ]  # fmt: skip
    assert all(p.is_file() for p in paths)


def test_custom_loop_detector_plugin(examples: dict[str, Example]) -> None:
    out = examples["plugin"].output()
    # `symbio detectors` listed it with the entry point's module:attribute.
    assert re.search(r"^  thumbnail +custom_loop_detector_plugin:create$", out, re.MULTILINE), out
    assert "plugin listed by `symbio detectors`: True" in out
    assert "loaded 'thumbnail' from custom_loop_detector_plugin:create" in out
    assert number(r"^thumbnail .*queries with a loop (\d+)", out) > 10
    assert number(r"^thumbnail .*recall_at_100p ([\d.]+)", out) > 0.0
    assert number(r"^vbow .*recall_at_100p ([\d.]+)", out) > 0.0


def test_plugin_entry_point_in_process() -> None:
    """The example's fake installation makes the registry load the detector, which honours its
    temporal window; leaving the block uninstalls it."""
    from lcd.base import LOOP_DETECTORS, LoopDetector

    example = runpy.run_path(str(EXAMPLES / "custom_loop_detector_plugin.py"), run_name="plugin_example")
    try:
        with example["installed_plugin"]():
            assert "thumbnail" in LOOP_DETECTORS.names()
            detector = LOOP_DETECTORS.load("thumbnail")(["temporal_window=2"])
            assert isinstance(detector, LoopDetector)
            images = [textured_image(seed) for seed in (1, 2, 3, 1)]
            answers = [
                detector.add(Keyframe(k, k, float(k), np.eye(4), image=image))
                for k, image in enumerate(images)
            ]
        assert "thumbnail" not in LOOP_DETECTORS.names()
    finally:
        sys.modules.pop("custom_loop_detector_plugin", None)
    assert answers[:3] == [[], [], []]  # keyframes 0-2: nothing outside the window yet
    assert [c.match for c in answers[3]] == [0]  # keyframe 3 may only match keyframe 0 ...
    assert answers[3][0].score == pytest.approx(1.0)  # ... and it is the same image
    assert answers[3][0].score >= detector.threshold


def test_evaluate_trajectory_evo_synthetic(examples: dict[str, Example]) -> None:
    out = examples["evo"].output()
    se3 = number(r"^APE RMSE after SE\(3\) align: +([\d.]+) m", out)
    sim3 = number(r"^APE RMSE after Sim\(3\) align: +([\d.]+) m", out)
    unaligned = number(r"^APE RMSE unaligned: +([\d.]+) m", out)
    assert sim3 < 0.1 * min(se3, unaligned)
    assert 0.0 < number(r"^RPE RMSE \(10 frames\), Sim\(3\): +([\d.]+) m", out) < sim3
    scale = number(r"^Sim\(3\) alignment: scale ([\d.]+)", out)
    assert scale == pytest.approx(number(r"^true scale ([\d.]+)", out), rel=0.05)


def test_evaluate_trajectory_evo_tum_files(examples: dict[str, Example]) -> None:
    out = examples["evo_files"].output()
    assert re.search(r": 100 associated poses$", out, re.MULTILINE), out
    assert number(r"^Sim\(3\) alignment: scale ([\d.]+)", out) == pytest.approx(2.0, rel=1e-3)
    assert number(r"^APE RMSE after Sim\(3\) align: +([\d.]+) m", out) < 1e-3
