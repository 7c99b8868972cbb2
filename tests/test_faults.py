"""Fault injection (``symbio run --inject``): each fault is handled as the README's "What we test
against" says, and the run's outputs stay consistent with each other.

Frame faults go through the reader's own decoding and the run's own skip-and-count path; plugin
faults through ``LoopClosing``'s plugin boundary and verification budget. The runs use the
session's 600-frame 320x240 synthetic loop scene (``small_loop_scene``).
"""

from __future__ import annotations

import csv
import json
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from eval.cli import main as symbio_main
from eval.inject import FRAME_FAULTS, InjectionSpec
from eval.run import LOOPS_FILE, METRICS_FILE, ODOMETRY_FILE, TRAJECTORY_FILE
from frontends.base import TrackResult
from frontends.datasets import open_dataset
from frontends.errors import ConfigError
from frontends.trajectory_io import read_tum
from frontends.types import Keyframe
from lcd.base import LoopCandidate
from slam_backend.pipeline import LoopClosing, LoopClosingConfig
from slam_backend.posegraph import BackendConfig, GtsamPoseGraph
from slam_backend.verify import Verification

FRAMES = 600


def symbio_run(scene: Path, out: Path, *extra: str) -> dict[str, Any]:
    argv = ["run", str(scene), "--no-progress", "--out", str(out), *extra]
    assert symbio_main(argv) == 0
    figures: dict[str, Any] = json.loads((out / METRICS_FILE).read_text())
    return figures


def replay(scene: Path, out: Path, *extra: str) -> dict[str, Any]:
    """The GT replayed (exact poses, fast), odometry only: what frame faults do to the stream."""
    trajectory = f"trajectory={scene / 'groundtruth.txt'}"
    return symbio_run(scene, out, "--frontend", "replay", "--set", trajectory, "--no-loops", *extra)


def loop_rows(out: Path) -> list[dict[str, str]]:
    with (out / LOOPS_FILE).open() as handle:
        return list(csv.DictReader(handle))


def assert_consistent(out: Path, figures: dict[str, Any], frames: int = FRAMES) -> None:
    """Every frame is processed or skipped; the files agree with the counts in metrics.json."""
    assert figures["frames"] + figures["frames_skipped"] == frames
    unposed = figures["tracking_lost"] + figures["frames_initialising"]
    assert figures["frames_tracked"] + unposed == figures["frames"]
    final, odometry = read_tum(out / TRAJECTORY_FILE), read_tum(out / ODOMETRY_FILE)
    assert final.num_poses == odometry.num_poses == figures["frames_tracked"]
    assert (np.diff(final.timestamps) > 0).all()
    rows = loop_rows(out)
    assert len(rows) == figures["loops_proposed"]
    assert sum(int(r["accepted"]) for r in rows) == figures["loops_accepted"]
    assert all(r["reason"] for r in rows if r["accepted"] == "0")
    assert not figures["interrupted"]


# --- the spec --------------------------------------------------------------------------------------------


def test_the_spec_parses_kinds_and_rates() -> None:
    spec = InjectionSpec.parse("black:0.1, corrupt-image,false-loops:1", seed=4)
    assert [(f.kind, f.rate) for f in spec.faults] == [
        ("black", 0.1),
        ("corrupt-image", 0.05),
        ("false-loops", 1.0),
    ]
    assert spec.seed == 4 and spec.rate("blur") == 0.0


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("blak", "unknown fault 'blak'"),
        ("black:x", "rate of black is not a number: 'x'"),
        ("black:0", r"rate of black must be in \(0, 1\]"),
        ("black:1.5", r"rate of black must be in \(0, 1\]"),
        ("black,black:0.2", "black given twice"),
    ],
)
def test_a_bad_spec_is_a_clear_error(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        InjectionSpec.parse(text)


def test_the_choice_of_frames_is_seeded() -> None:
    text = ",".join(f"{kind}:0.05" for kind in FRAME_FAULTS)
    plans = [[InjectionSpec.parse(text, seed).frame_fault(i) for i in range(FRAMES)] for seed in (1, 1, 2)]
    assert plans[0] == plans[1] != plans[2]
    hit = sum(kind is not None for kind in plans[0])
    assert 0.25 * FRAMES < hit < 0.55 * FRAMES  # 8 faults at 5 %: ~34 %


def test_plugin_faults_need_the_plugins(
    small_loop_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["run", str(small_loop_scene), "--no-loops", "--inject", "false-loops", "--out", str(tmp_path)]
    assert symbio_main(argv) == 2
    assert "--inject false-loops: this run has no such plugin" in capsys.readouterr().err


# --- frame faults ----------------------------------------------------------------------------------------


def test_undecodable_images_are_skipped_counted_and_named(
    small_loop_scene: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    out = tmp_path / "run"
    figures = replay(
        small_loop_scene, out, "--inject", "corrupt-image:0.05,truncated-image:0.05,wrong-size:0.05"
    )
    undecodable = figures["faults_injected_corrupt_image"] + figures["faults_injected_truncated_image"]
    assert figures["faults_injected_corrupt_image"] > 10 and figures["faults_injected_truncated_image"] > 10
    assert figures["frames_skipped_undecodable_image"] == undecodable
    assert figures["frames_skipped_wrong_image_size"] == figures["faults_injected_wrong_size"] > 10
    injected = undecodable + figures["faults_injected_wrong_size"]
    assert figures["frames_skipped"] == injected
    assert_consistent(out, figures)
    assert figures["frames_tracked"] == FRAMES - injected and figures["ate_rmse_before"] < 1e-6
    # The warning names the index file and line of each skipped frame.
    messages = [r.getMessage() for r in caplog.records]
    skipped_lines = [m for m in messages if "image does not decode" in m or "the camera's calibration" in m]
    assert len(skipped_lines) == injected
    assert any("image is 160x120, the camera's calibration is for 320x240" in m for m in messages)
    assert all(f"{small_loop_scene / 'rgb.txt'}:" in line for line in skipped_lines)
    # No skipped frame has a pose.
    stamps = open_dataset(small_loop_scene).timestamps
    posed = set(read_tum(out / TRAJECTORY_FILE).timestamps.round(6))
    assert len(posed & set(stamps.round(6))) == figures["frames_tracked"]


@pytest.mark.slow
def test_missing_images_are_skipped_counted_and_named(small_loop_scene: Path, tmp_path: Path) -> None:
    scene = tmp_path / "scene"  # the scene's rgb.txt, listing absolute paths, two of them absent
    scene.mkdir()
    for name in ("groundtruth.txt", "intrinsics.yaml"):
        (scene / name).write_bytes((small_loop_scene / name).read_bytes())
    lines = []
    for line in (small_loop_scene / "rgb.txt").read_text().splitlines():
        stamp, _, name = line.partition(" ")
        lines.append(line if line.startswith("#") else f"{stamp} {small_loop_scene / name}")
    data = [k for k, line in enumerate(lines) if not line.startswith("#")]
    for k in (data[10], data[300]):
        lines[k] = lines[k].replace(".png", "-gone.png")
    (scene / "rgb.txt").write_text("\n".join(lines) + "\n")
    figures = replay(scene, tmp_path / "run")
    assert figures["frames_skipped"] == figures["frames_skipped_missing_image"] == 2
    assert_consistent(tmp_path / "run", figures)
    assert figures["frames_tracked"] == FRAMES - 2 and figures["ate_rmse_before"] < 1e-6


def test_strict_makes_an_undecodable_image_an_error_after_writing_what_exists(
    small_loop_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "run"
    trajectory = f"trajectory={small_loop_scene / 'groundtruth.txt'}"
    argv = [
        "run",
        str(small_loop_scene),
        "--frontend",
        "replay",
        "--set",
        trajectory,
        "--no-loops",
        "--strict",
    ]
    assert symbio_main([*argv, "--no-progress", "--inject", "truncated-image:0.05", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{small_loop_scene / 'rgb.txt'}:" in err and "image does not decode" in err
    figures = json.loads((out / METRICS_FILE).read_text())
    assert figures["interrupted"] is True and figures["frames"] == figures["frames_tracked"] > 0


@pytest.mark.slow
def test_duplicate_and_backwards_timestamps_are_skipped_and_counted(
    small_loop_scene: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    out = tmp_path / "run"
    figures = replay(small_loop_scene, out, "--inject", "duplicate-timestamp:0.05,backwards-timestamp:0.05")
    duplicates, backwards = (
        figures["faults_injected_duplicate_timestamp"],
        figures["faults_injected_backwards_timestamp"],
    )
    assert duplicates > 10 and backwards > 10
    # A backwards stamp right after a duplicate may equal the last frame's stamp: the sum is exact.
    skipped = figures["frames_skipped_duplicate_timestamp"] + figures["frames_skipped_backwards_timestamp"]
    assert skipped == figures["frames_skipped"] == duplicates + backwards
    assert (
        figures["frames_skipped_backwards_timestamp"] > 0
        and figures["frames_skipped_duplicate_timestamp"] > 0
    )
    assert_consistent(out, figures)
    assert figures["ate_rmse_before"] < 1e-6
    assert f"{small_loop_scene / 'rgb.txt'}:" in caplog.text and "backwards timestamp" in caplog.text


# --- the verification budget ---------------------------------------------------------------------------


class Previous:
    """A loop detector that proposes the previous keyframe, with a high score."""

    name = "previous"
    threshold = 0.5

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]:
        return [LoopCandidate(keyframe.id, keyframe.id - 1, 1.0)] if keyframe.id else []


class Stuck:
    """A verifier that does not answer until ``release`` is set."""

    name = "stuck"

    def __init__(self) -> None:
        self.release = threading.Event()
        self.calls = 0

    def verify(self, query: Keyframe, match: Keyframe) -> Verification:
        self.calls += 1
        self.release.wait()
        return Verification(query.id, match.id, False, "answered")


def test_the_budget_must_be_positive() -> None:
    with pytest.raises(ConfigError, match="verify_timeout_s must be positive"):
        LoopClosingConfig(verify_timeout_s=0)


def test_a_verifier_past_its_budget_rejects_the_candidate_with_reason_timeout() -> None:
    verifier = Stuck()
    # Once released, a late call returns well within this; decided when the keyframe is added.
    config = LoopClosingConfig(verify_timeout_s=0.5, overlap_verification=False)
    closing = LoopClosing(GtsamPoseGraph(BackendConfig()), Previous(), None, verifier, config)  # type: ignore[arg-type]

    def add(k: int) -> None:
        pose = np.eye(4)
        pose[0, 3] = 0.1 * k
        closing.add(TrackResult(k, float(k), "tracking", pose, 0, Keyframe(k, k, float(k), pose)))

    for k in range(3):
        add(k)
    reasons = [r.reason for r in closing.loops()]
    assert reasons == [
        "timeout: no answer within 0.5 s",
        "timeout: the verifier is still busy with an earlier candidate",
    ]
    assert verifier.calls == 1  # never called while an earlier call runs
    verifier.release.set()
    add(3)
    assert closing.loops()[-1].reason == "answered"
    assert closing.counters.verifier_timeouts == 2 and closing.counters.verifier_failures == 0
    assert len(closing.frame_poses(corrected=True)) == 4


def test_overlapped_verification_is_decided_at_the_next_keyframe_with_the_same_budget() -> None:
    """The default: a keyframe's candidates are verified on a worker while later frames track, and
    decided when the next keyframe comes (or at finish); the budget and the timeouts hold as above."""
    verifier = Stuck()
    closing = LoopClosing(
        GtsamPoseGraph(BackendConfig()),
        Previous(),
        None,
        verifier,
        LoopClosingConfig(verify_timeout_s=0.5),  # type: ignore[arg-type]
    )

    def add(k: int) -> None:
        pose = np.eye(4)
        pose[0, 3] = 0.1 * k
        closing.add(TrackResult(k, float(k), "tracking", pose, 0, Keyframe(k, k, float(k), pose)))

    add(0)
    add(1)  # 1 -> 0 handed to the worker, not decided yet
    assert closing.loops() == [] and verifier.calls == 1
    add(2)  # 1 -> 0 decided (past its budget); 2 -> 1 cannot start while the stuck call runs
    assert [r.reason for r in closing.loops()] == ["timeout: no answer within 0.5 s"]
    verifier.release.set()
    add(3)  # 2 -> 1 decided as busy; 3 -> 2 runs now
    closing.finish()  # and is decided here
    assert [r.reason for r in closing.loops()] == [
        "timeout: no answer within 0.5 s",
        "timeout: the verifier is still busy with an earlier candidate",
        "answered",
    ]
    assert verifier.calls == 2
    assert closing.counters.verifier_timeouts == 2


# --- the full pipeline: mono-vo, symbiolcd2, pycolmap, gtsam -------------------------------------------


def posed_frames(scene: Path, out: Path) -> set[int]:
    """Indices of the frames that have a pose in the run's trajectory."""
    stamps = open_dataset(scene).timestamps
    posed = read_tum(out / TRAJECTORY_FILE).timestamps
    return set(np.flatnonzero(np.isin(stamps.round(6), posed.round(6))).tolist())


STARVING = "black:0.03,no-features:0.03,overexposed:0.03,blur:0.03"


@pytest.mark.slow
def test_frames_without_usable_features_are_lost_never_posed(small_loop_scene: Path, tmp_path: Path) -> None:
    out, frames = tmp_path / "run", 400
    argv = ["--no-loops", "--max-frames", str(frames), "--inject", STARVING, "--inject-seed", "2"]
    figures = symbio_run(small_loop_scene, out, *argv)
    spec = InjectionSpec.parse(STARVING, 2)
    plan = {i: spec.frame_fault(i) for i in range(frames)}
    empty = {i for i, kind in plan.items() if kind in ("black", "no-features")}
    assert len(empty) == figures["faults_injected_black"] + figures["faults_injected_no_features"] > 15
    assert figures["faults_injected_overexposed"] > 5 and figures["faults_injected_blur"] > 5
    assert figures["frames_skipped"] == 0
    assert_consistent(out, figures, frames)
    # A black or flat frame gets no pose (it would be invented); tracking resumes after it.
    assert not empty & posed_frames(small_loop_scene, out)
    assert figures["tracking_lost"] + figures["frames_initialising"] >= len(empty)
    assert figures["frames_tracked"] > 0.8 * frames


PLUGINS = "objects-raise:0.3,objects-empty:0.3,loops-raise:0.2,verifier-raise:0.3,verifier-timeout:0.5"


@pytest.mark.slow
def test_failing_plugins_cost_one_keyframe_or_candidate_each(small_loop_scene: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    budget = "loop_closing.verify_timeout_s=0.2"
    figures = symbio_run(small_loop_scene, out, "--inject", PLUGINS, "--set", budget)
    assert figures["object_detector_failures"] == figures["faults_injected_objects_raise"] > 5
    assert figures["faults_injected_objects_empty"] > 5
    assert figures["loop_detector_failures"] == figures["faults_injected_loops_raise"] > 5
    rows = loop_rows(out)
    # A retry's error reads "rejected after deferral: verifier error: ...".
    errors = [r for r in rows if "verifier error: " in r["reason"]]
    timeouts = [r for r in rows if r["reason"].startswith("timeout")]
    assert len(errors) == figures["verifier_failures"] == figures["faults_injected_verifier_raise"] > 0
    assert all("injected verifier-raise" in r["reason"] for r in errors)
    # A slow call delays the next candidate at most one budget; under load that one may time out too.
    assert len(timeouts) == figures["verifier_timeouts"] >= figures["faults_injected_verifier_timeout"] > 0
    assert not any(int(r["verified"]) for r in errors + timeouts)
    assert_consistent(out, figures)
    assert figures["keyframes"] > 50 and figures["frames_tracked"] > 0.8 * FRAMES


#: Frames of the false-loop runs: past the start of the second lap (frame ~430).
LAP_FRAMES = 450


@pytest.fixture(scope="module")
def clean_run(small_loop_scene: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The same run without injected faults and without moving the frontend's map after a loop, so
    its odometry ("before") is what the frontend builds when no loop touches it."""
    return symbio_run(
        small_loop_scene, tmp_path_factory.mktemp("clean") / "run", "--max-frames", str(LAP_FRAMES),
        "--set", "loop_closing.correct_frontend=false",
    )  # fmt: skip


@pytest.mark.slow
def test_false_loops_are_rejected_and_the_map_stays_as_good(
    small_loop_scene: Path, tmp_path: Path, clean_run: dict[str, Any]
) -> None:
    out = tmp_path / "run"
    figures = symbio_run(small_loop_scene, out, "--inject", "false-loops", "--max-frames", str(LAP_FRAMES))
    assert_consistent(out, figures, LAP_FRAMES)
    rows = loop_rows(out)
    assert len(rows) == figures["faults_injected_false_loops"] > 40
    gt = open_dataset(small_loop_scene).gt_poses
    assert gt is not None
    for row in rows:  # every proposal joins places at least 2 m apart
        query, match = gt[int(row["query_frame"])], gt[int(row["match_frame"])]
        assert np.linalg.norm(query[:3, 3] - match[:3, 3]) >= 2.0
    assert figures["loops_accepted"] == figures["false_loops_accepted"] == 0
    assert figures["ate_rmse_after"] == pytest.approx(clean_run["ate_rmse_before"], rel=1e-6)
    # Nothing moved the map: the loop-closed trajectory is the odometry, both segments included (the
    # clean run's true loops join the two segments, which no false loop may do).
    final, odometry = read_tum(out / TRAJECTORY_FILE), read_tum(out / ODOMETRY_FILE)
    np.testing.assert_allclose(final.positions_xyz, odometry.positions_xyz, atol=1e-9)


@pytest.mark.slow
def test_verified_false_loops_are_rejected_by_the_backend() -> None:
    """Rendered keyframes with exact depth and simulated drift (``test_pipeline``), one map segment:
    every false pair passes "verification" with a confident identity constraint, as perceptual
    aliasing would make it; PCM + GNC must keep all of them out, so the loop-closed trajectory stays
    the odometry's."""
    from test_pipeline import RenderedObjects, ate, drifting_keyframes

    from eval.bench.synth_keyframes import scene_camera
    from eval.inject import FaultyLoopDetector, FaultyVerifier, Injection
    from frontends.synth.render import SceneRenderer
    from frontends.synth.world import SynthConfig
    from frontends.types import Frame
    from lcd.symbiolcd2 import create as create_symbiolcd2
    from slam_backend.verify import create as create_verifier

    injection = Injection(InjectionSpec.parse("false-loops-verified"))
    renderer = SceneRenderer(SynthConfig(trajectory="loop", seed=3))
    objects = RenderedObjects()
    keyframes = list(drifting_keyframes("loop", 3))
    centres = np.full((renderer.config.frames, 3), np.nan)
    for keyframe, _, gt in keyframes:
        centres[keyframe.frame_index] = gt[:3, 3]
    closing = LoopClosing(
        GtsamPoseGraph(BackendConfig()),
        FaultyLoopDetector(create_symbiolcd2(), injection, centres),
        objects,
        FaultyVerifier(create_verifier(scene_camera(renderer)), injection, 0.0),
    )
    for keyframe, rendered, _ in keyframes:
        objects.remember(rendered)
        result = TrackResult(keyframe.frame_index, keyframe.timestamp, "tracking", keyframe.pose, 0, keyframe)
        closing.add(result, Frame(keyframe.frame_index, keyframe.timestamp, rendered.image))
    gt = [g for _, _, g in keyframes]
    closing.finish()  # the last keyframe's candidates are decided here (overlap_verification)
    # The final estimate first: it runs the GNC pass that is due, which may revise PCM's decisions.
    after = ate([p for _, _, p in closing.frame_poses(corrected=True)], gt)
    before = ate([p for _, _, p in closing.frame_poses(corrected=False)], gt)
    assert after == pytest.approx(before, rel=0.05)
    loops = closing.loops()
    assert len(loops) == injection.counts["false-loops-verified"] > 60
    assert all(r.verified for r in loops)
    assert not any(r.accepted for r in loops) and all(r.reason == "rejected by the backend" for r in loops)
