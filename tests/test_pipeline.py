"""Loop closing end to end: detector -> verifier -> Sim(3) pose graph, on rendered keyframes.

The keyframes come straight from the synthetic renderer (every 6th frame of a 20 s 640x480 scene),
with exact map points from its depth buffer (``eval.bench.synth_keyframes``) and GT objects with 30 %
misses, and poses that drift like monocular odometry (a slow scale shrink and a yaw bias). So the
detector, the pycolmap verifier and the GTSAM backend run on realistic images and geometry, while
the trajectory error before loop closing is known and large. The full ``symbio run`` with the
``mono-vo`` frontend is tested in ``test_symbio_run_*``.
"""

from __future__ import annotations

import csv
import itertools
import json
from collections.abc import Iterator, Sequence
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from evo.core import metrics
from evo.core.trajectory import PoseTrajectory3D
from scipy.spatial.transform import Rotation

from eval.bench.synth_keyframes import keyframe_with_depth, scene_camera
from eval.cli import main as symbio_main
from eval.components import load_components
from eval.demo import synthetic_components
from eval.run import LOOPS_FILE, METRICS_FILE, ODOMETRY_FILE, TRAJECTORY_FILE, loop_truth
from frontends.base import TrackResult
from frontends.synth.covisibility import CovisibilityLabelConfig, overlap_matrix
from frontends.synth.render import RenderedFrame, SceneRenderer
from frontends.synth.world import SynthConfig
from frontends.trajectory_io import read_tum
from frontends.types import DetectedObject, Frame, Keyframe
from lcd.base import LoopCandidate
from lcd.symbiolcd2 import create as create_symbiolcd2
from slam_backend.pipeline import LoopClosing, LoopClosingConfig, LoopRecord
from slam_backend.posegraph import BackendConfig, GtsamPoseGraph
from slam_backend.verify import Verification
from slam_backend.verify import create as create_verifier

KEYFRAME_EVERY = 6
MISS_RATE = 0.3


class RenderedObjects:
    """GT objects of the rendered keyframes, each missed with probability 0.3 (seeded per frame)."""

    name = "rendered-gt"

    def __init__(self) -> None:
        self.frames: dict[int, tuple[DetectedObject, ...]] = {}

    def remember(self, rendered: RenderedFrame) -> None:
        rng = np.random.default_rng([11, rendered.index])
        self.frames[rendered.index] = tuple(
            DetectedObject(o.label, 1.0, tuple(float(v) for v in o.box), instance=o.instance)
            for o in rendered.objects
            if not o.movable and rng.random() >= MISS_RATE and o.visible_fraction >= 0.3
        )

    def detect(self, image: np.ndarray, frame: Frame | None = None) -> list[DetectedObject]:
        assert frame is not None
        return list(self.frames[frame.index])


def drifting_keyframes(trajectory: str, seed: int) -> Iterator[tuple[Keyframe, RenderedFrame, np.ndarray]]:
    """(keyframe with drifted pose and scaled map points, rendered frame, GT pose)."""
    renderer = SceneRenderer(SynthConfig(trajectory=trajectory, seed=seed))  # type: ignore[arg-type]
    previous_gt = previous_drifted = None
    for kf_id, index in enumerate(range(0, renderer.config.frames, KEYFRAME_EVERY)):
        keyframe = keyframe_with_depth(renderer, index, kf_id)
        rendered = renderer.frame(index)
        gt = keyframe.pose.copy()
        # Odometry: GT steps, scaled and rotated by the accumulated drift.
        if previous_gt is None:
            drifted = gt.copy()
        else:
            step = np.linalg.inv(previous_gt) @ gt
            step[:3, 3] *= 0.997**kf_id
            yaw = np.eye(4)
            yaw[:3, :3] = Rotation.from_euler("y", 0.25, degrees=True).as_matrix()
            drifted = previous_drifted @ step @ yaw
        previous_gt, previous_drifted = gt, drifted
        assert keyframe.points3d is not None
        scaled = replace(
            keyframe,
            pose=drifted,
            points3d=keyframe.points3d * 0.997**kf_id,
            odometry_covariance=np.diag([1e-5] * 3 + [(0.02 * 0.1) ** 2] * 3 + [0.01**2]),
        )
        yield scaled, rendered, gt


def close_loops(
    trajectory: str, seed: int, detector: object | None = None
) -> tuple[LoopClosing, list[np.ndarray], list[Keyframe]]:
    renderer_camera = scene_camera(SceneRenderer(SynthConfig(trajectory=trajectory, seed=seed)))  # type: ignore[arg-type]
    objects = RenderedObjects()
    closing = LoopClosing(
        GtsamPoseGraph(BackendConfig()),
        detector if detector is not None else create_symbiolcd2(),  # type: ignore[arg-type]
        objects,
        create_verifier(renderer_camera),
    )
    gt_poses, keyframes = [], []
    for keyframe, rendered, gt in drifting_keyframes(trajectory, seed):
        objects.remember(rendered)
        result = TrackResult(keyframe.frame_index, keyframe.timestamp, "tracking", keyframe.pose, 0, keyframe)
        closing.add(result, Frame(keyframe.frame_index, keyframe.timestamp, rendered.image))
        gt_poses.append(gt)
        keyframes.append(keyframe)
    return closing, gt_poses, keyframes


def ate(poses: Sequence[np.ndarray], gt: Sequence[np.ndarray]) -> float:
    stamps = np.arange(len(poses), dtype=np.float64)
    estimate = PoseTrajectory3D(poses_se3=list(poses), timestamps=stamps)
    reference = PoseTrajectory3D(poses_se3=list(gt), timestamps=stamps)
    estimate.align(reference, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((reference, estimate))
    return float(ape.get_statistic(metrics.StatisticsType.rmse))


@pytest.fixture(scope="module")
def loop_run() -> tuple[LoopClosing, list[np.ndarray], list[Keyframe]]:
    return close_loops("loop", 3)


def test_a_revisit_is_found_verified_and_reduces_the_error(
    loop_run: tuple[LoopClosing, list[np.ndarray], list[Keyframe]],
) -> None:
    closing, gt, _keyframes = loop_run
    loops = closing.loops()
    accepted = [r for r in loops if r.accepted]
    assert len(accepted) >= 3
    # Every accepted loop joins two views of the same surfaces: each sees more than `leave_overlap`
    # of the other's, the labeller's "still there". (GT loop labels also want 1 m and 30 %, a choice
    # for recall: a right loop 1.05 m apart, overlaps 0.29 / 0.56, is accepted here with the exact
    # drifted scale.)
    renderer, labels = SceneRenderer(SynthConfig(trajectory="loop", seed=3)), CovisibilityLabelConfig()
    for loop in accepted:
        grids, poses = [], []
        for index in (loop.query_frame, loop.match_frame):
            poses.append(renderer.frame(index).pose)
            grids.append(renderer.depth_samples(labels.depth_step))
        overlap = overlap_matrix(np.stack(grids), np.stack(poses), renderer.config.intrinsics, labels)
        assert min(overlap[0, 1], overlap[1, 0]) > labels.leave_overlap, (loop, overlap)
        # The verifier recovers the drifted scale between the two maps (0.997 per keyframe).
        assert loop.scale == pytest.approx(0.997 ** (loop.match - loop.query), rel=0.05)
    before = ate([p for _, _, p in closing.frame_poses(corrected=False)], gt)
    after = ate([p for _, _, p in closing.frame_poses(corrected=True)], gt)
    assert after < 0.5 * before, (before, after)


def test_keyframe_images_are_released_once_loop_detection_used_them(
    loop_run: tuple[LoopClosing, list[np.ndarray], list[Keyframe]],
) -> None:
    closing, _, keyframes = loop_run
    # The detector saw every keyframe's objects (found from its image) and the images are gone:
    # a long run keeps no 0.9 MB per keyframe.
    assert closing.detector is not None
    assert closing.detector.object_poor_keyframes < len(keyframes)  # type: ignore[attr-defined]
    assert all(k.image is None for k in closing.keyframes)
    kept = LoopClosing(
        GtsamPoseGraph(BackendConfig()), None, None, None, LoopClosingConfig(keep_keyframe_images=True)
    )
    frame = Frame(0, 0.0, np.zeros((8, 8, 3), np.uint8))
    keyframe = replace(keyframes[0], image=frame.image)
    kept.add(TrackResult(0, 0.0, "tracking", keyframe.pose, 0, keyframe), frame)
    kept.finish()
    assert kept.keyframes[0].image is not None


def test_finish_releases_the_loop_detectors_database() -> None:
    detector = create_symbiolcd2()
    closing = LoopClosing(GtsamPoseGraph(BackendConfig()), detector, None, None)
    keyframes = [k for k, _, _ in itertools.islice(drifting_keyframes("loop", 3), 12)]
    for keyframe in keyframes:
        result = TrackResult(keyframe.frame_index, keyframe.timestamp, "tracking", keyframe.pose, 0, keyframe)
        closing.add(result)
    closing.finish()
    # Every keyframe reached the detector, and its database went before the end-of-run work.
    assert len(detector.keyframe_ids) == len(keyframes)
    assert len(detector.kernel) == 0


class FalseLoops:
    """A loop detector that proposes, with a high score, the keyframe half a lap before the query."""

    name = "false-loops"
    threshold = 0.5

    def __init__(self, offset: int) -> None:
        self.offset = offset
        self.seen = 0

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]:
        self.seen += 1
        if keyframe.id < self.offset:
            return []
        return [LoopCandidate(keyframe.id, keyframe.id - self.offset, 10.0, {"forced": 1.0})]


@pytest.mark.slow
def test_forced_false_candidates_are_rejected_and_leave_the_trajectory_unchanged() -> None:
    # 100 keyframes per 1.4 laps: 35 keyframes back is half a lap, the other side of the room.
    closing, _, _ = close_loops("loop", 3, FalseLoops(35))
    loops = closing.loops()
    assert len(loops) >= 60
    assert not any(r.accepted for r in loops)
    assert all(r.reason for r in loops)
    odometry = np.array([p for _, _, p in closing.frame_poses(corrected=False)])
    final = np.array([p for _, _, p in closing.frame_poses(corrected=True)])
    np.testing.assert_allclose(final, odometry, atol=1e-6)


@pytest.mark.slow
def test_no_revisit_no_loop() -> None:
    closing, _, _ = close_loops("none", 4)
    assert not any(r.accepted for r in closing.loops())


class Raising:
    name = "raising"
    threshold = 0.0

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]:
        raise RuntimeError("detector bug")

    def detect(self, image: np.ndarray, frame: Frame | None = None) -> list[DetectedObject]:
        raise RuntimeError("object detector bug")

    def verify(self, query: Keyframe, match: Keyframe) -> None:
        raise RuntimeError("verifier bug")


def test_failing_plugins_cost_one_keyframe_each(
    loop_run: tuple[LoopClosing, list[np.ndarray], list[Keyframe]],
) -> None:
    # The run released its keyframes' images (loop_closing.keep_keyframe_images); the object
    # detector is asked only about keyframes with one.
    keyframes = [replace(k, image=np.zeros((48, 64, 3), np.uint8)) for k in loop_run[2]]
    closing = LoopClosing(GtsamPoseGraph(BackendConfig()), Raising(), Raising())  # type: ignore[arg-type]
    for keyframe in keyframes[:20]:
        closing.add(
            TrackResult(keyframe.frame_index, keyframe.timestamp, "tracking", keyframe.pose, 0, keyframe)
        )
    assert closing.counters.loop_detector_failures == 20
    assert closing.counters.object_detector_failures == 20
    assert len(closing.frame_poses(corrected=True)) == 20
    verifying = LoopClosing(
        GtsamPoseGraph(BackendConfig()),
        FalseLoops(5),
        None,
        Raising(),  # type: ignore[arg-type]
    )
    for keyframe in keyframes[:10]:
        verifying.add(
            TrackResult(keyframe.frame_index, keyframe.timestamp, "tracking", keyframe.pose, 0, keyframe)
        )
    verifying.finish()  # the last keyframe's verifications are decided here (overlap_verification)
    assert verifying.counters.verifier_failures == 5
    assert all(not r.verified and "verifier bug" in r.reason for r in verifying.loops())


def test_frames_before_a_segments_first_keyframe_are_anchored_to_it(
    loop_run: tuple[LoopClosing, list[np.ndarray], list[Keyframe]],
) -> None:
    """A frontend may pose frames before a new map's first keyframe (tracked backwards from it) and
    hand them back with that keyframe: they are anchored to it, not dropped."""
    _, _, keyframes = loop_run
    closing = LoopClosing(GtsamPoseGraph(BackendConfig()))
    first, second = keyframes[1], keyframes[2]
    earlier = replace(first, frame_index=first.frame_index - 2, timestamp=first.timestamp - 0.1)
    backfilled = (
        TrackResult(earlier.frame_index, earlier.timestamp, "tracking", first.pose, 0),
        TrackResult(first.frame_index, first.timestamp, "tracking", first.pose, 0, first),
    )
    result = TrackResult(second.frame_index, second.timestamp, "tracking", second.pose, 0, second, backfilled)
    closing.add(result)
    closing.finish()
    poses = {index: pose for index, _, pose in closing.frame_poses(corrected=False)}
    assert sorted(poses) == [earlier.frame_index, first.frame_index, second.frame_index]
    np.testing.assert_allclose(poses[earlier.frame_index], poses[first.frame_index], atol=1e-9)


# --- the command line ---------------------------------------------------------------------------------


def test_run_config_sections_and_overrides(tmp_path: Path) -> None:
    config = tmp_path / "run.yaml"
    config.write_text(
        yaml.safe_dump(
            {
                "frontend": {"name": "mono-vo", "orb": {"nfeatures": 1000}},
                "detector": {"name": "vbow", "threshold": 0.2},
                "backend": {"rejection": "pcm"},
            }
        )
    )
    components = load_components(
        config, ["detector.threshold=0.3", "seed=4", "verifier.ratio=0.7"], {"backend": None}
    )
    assert components.frontend == "mono-vo" and components.detector == "vbow"
    assert components.of("frontend") == ["orb.nfeatures=1000", "seed=4"]
    assert components.of("detector") == ["threshold=0.2", "threshold=0.3"]
    assert components.of("verifier") == ["ratio=0.7"]
    assert components.of("backend") == ["rejection=pcm"]
    plain = tmp_path / "frontend.yaml"
    plain.write_text("orb:\n  nfeatures: 900\n")
    assert load_components(plain, [], {}).of("frontend") == ["orb.nfeatures=900"]


def test_symbio_run_writes_every_output(small_loop_scene: Path, tmp_path: Path) -> None:
    out = tmp_path / "run"
    argv = ["run", str(small_loop_scene), "--max-frames", "200", "--no-progress", "--out", str(out)]
    assert symbio_main(argv) == 0
    figures = json.loads((out / METRICS_FILE).read_text())
    assert figures["loop_closing"] is True and figures["detector"] == "symbiolcd2"
    for key in ("ate_rmse_before", "ate_rmse_after", "rpe_rmse_before", "rpe_rmse_after", "fps"):
        assert figures[key] is not None and np.isfinite(figures[key]), key
    assert figures["false_loops_accepted"] == 0
    assert figures["global_ba"] is (figures["loops_accepted"] > 0)
    final, odometry = read_tum(out / TRAJECTORY_FILE), read_tum(out / ODOMETRY_FILE)
    assert final.num_poses == odometry.num_poses == figures["frames_tracked"]
    with (out / LOOPS_FILE).open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == figures["loops_proposed"]
    for name in ("report.html", "trajectory_top.png", "ape_over_time.png", "keyframes_tum.txt"):
        assert (out / name).stat().st_size > 0, name
    assert "Configuration" in (out / "report.html").read_text()


@pytest.mark.slow
def test_symbio_demo_closes_its_loops(demo_run: Path) -> None:
    """The embedded default halves the odometry's error with verified, true loops."""
    figures = json.loads((demo_run / METRICS_FILE).read_text())
    assert figures["frames_tracked"] == figures["frames"] and figures["segments"] == 1
    assert figures["loops_accepted"] >= 5 and figures["false_loops_accepted"] == 0
    assert figures["ate_rmse_after"] <= 0.5 * figures["ate_rmse_before"]
    for name in ("report.html", "trajectory_top.png", "ape_over_time.png", TRAJECTORY_FILE, LOOPS_FILE):
        assert (demo_run / name).stat().st_size > 0, name


@pytest.mark.slow
def test_the_global_bundle_adjustment_ends_a_run_with_loops(demo_run: Path, tmp_path: Path) -> None:
    """Accepted loops end in a global bundle adjustment that lowers the reprojection error and
    re-poses the tracked frames, and ``--set`` turns it off. (Whether it improves the trajectory
    is measured by ``eval/bench/pipeline.py`` and ``tests/test_global_ba.py``.) The demo ran with
    it; the same scene and components run again without it."""
    out = tmp_path / "graph_only"
    argv = ["run", str(demo_run / "scene"), "--no-progress", "--out", str(out)]
    demo = synthetic_components()
    argv += ["--object-detector", demo.object_detector]
    for item in demo.of("object_detector"):
        argv += ["--set", f"object_detector.{item}"]
    assert symbio_main([*argv, "--set", "loop_closing.global_ba.enabled=false"]) == 0
    adjusted = json.loads((demo_run / METRICS_FILE).read_text())
    graph_only = json.loads((out / METRICS_FILE).read_text())
    assert adjusted["loops_accepted"] > 0 and adjusted["global_ba"] is True
    assert graph_only["global_ba"] is False
    assert adjusted["global_ba_median_error_px_after"] < adjusted["global_ba_median_error_px_before"]
    assert adjusted["global_ba_loop_observations"] > 0
    assert 0.5 * adjusted["frames_tracked"] < adjusted["frames_reposed"] <= adjusted["frames_tracked"]
    # The odometry is the same run's; only what the loops make of it differs.
    assert adjusted["ate_rmse_before"] == pytest.approx(graph_only["ate_rmse_before"], rel=1e-9)
    assert adjusted["ate_rmse_after_all"] != graph_only["ate_rmse_after_all"]


@pytest.mark.slow
def test_symbio_run_viewer_writes_a_recording(small_loop_scene: Path, tmp_path: Path) -> None:
    pytest.importorskip("rerun")
    out = tmp_path / "run"
    argv = ["run", str(small_loop_scene), "--max-frames", "60", "--viewer", "rerun", "--no-progress"]
    assert symbio_main([*argv, "--out", str(out)]) == 0
    assert (out / "run.rrd").stat().st_size > 10_000


@pytest.mark.slow
def test_two_runs_give_byte_identical_outputs(small_loop_scene: Path, tmp_path: Path) -> None:
    outputs = []
    for name in ("a", "b"):
        out = tmp_path / name
        argv = ["run", str(small_loop_scene), "--max-frames", "150", "--no-progress", "--out", str(out)]
        assert symbio_main(argv) == 0
        outputs.append(out)
    for name in (TRAJECTORY_FILE, ODOMETRY_FILE, "keyframes_tum.txt", LOOPS_FILE):
        assert (outputs[0] / name).read_bytes() == (outputs[1] / name).read_bytes(), name


def test_a_bad_run_config_names_the_file(tmp_path: Path) -> None:
    from frontends.errors import ConfigError

    bad = tmp_path / "run.yaml"
    bad.write_text("detector:\n  name: vbow\nverifer:\n  ratio: 0.7\n")
    with pytest.raises(ConfigError, match=r"run\.yaml:3: unknown section 'verifer'"):
        load_components(bad, [], {})
    bad.write_text("detector: vbow\n")
    with pytest.raises(ConfigError, match=r"run\.yaml:1: section 'detector' must be a mapping"):
        load_components(bad, [], {})


class _GroundTruth:
    """What ``loop_truth`` reads of a dataset: GT poses and GT loop pairs."""

    def __init__(self, poses: np.ndarray | None, pairs: np.ndarray | None) -> None:
        self.gt_poses = poses
        self._pairs = pairs

    def loop_pairs(self) -> tuple[np.ndarray | None, None]:
        return self._pairs, None


def _accepted(query_frame: int, match_frame: int, relative: np.ndarray) -> LoopRecord:
    return LoopRecord(
        query_frame, match_frame, query_frame, match_frame, 1.0, True, 80, True, "", 1.0, 0, relative
    )


def test_a_false_loop_is_a_constraint_that_contradicts_the_gt_poses() -> None:
    """A right constraint outside the labeller's band is not false; a wrong one inside it is."""
    poses = np.repeat(np.eye(4)[None], 40, axis=0)
    poses[:, 0, 3] = np.arange(40) * 0.1  # straight line, 10 cm per frame
    right = np.linalg.inv(poses[10]) @ poses[30]
    wrong = np.linalg.inv(poses[2]) @ poses[31]
    wrong[:3, :3] = Rotation.from_euler("y", 20, degrees=True).as_matrix()
    loops = [_accepted(30, 10, right), _accepted(31, 2, wrong)]
    keyframes = [SimpleNamespace(frame_index=i) for i in range(40)]
    pairs = np.array([[31, 2], [30, 25]])
    figures = loop_truth(_GroundTruth(poses, pairs), loops, keyframes, tolerance=0)  # type: ignore[arg-type]
    assert figures["false_loops_accepted"] == 1
    assert figures["loops_outside_gt_band"] == 1 and figures["lcd_precision"] == 0.5
    # Without GT poses the band is all there is; without either, nothing is known.
    assert loop_truth(_GroundTruth(None, pairs), loops, keyframes, 0)["false_loops_accepted"] == 1  # type: ignore[arg-type]
    only_poses = loop_truth(_GroundTruth(poses, None), loops, keyframes, 0)  # type: ignore[arg-type]
    assert only_poses["false_loops_accepted"] == 1 and only_poses["loops_outside_gt_band"] is None
    assert loop_truth(_GroundTruth(None, None), loops, keyframes, 0)["false_loops_accepted"] is None  # type: ignore[arg-type]


class ThreeCandidates:
    """Proposes, for every keyframe from the 12th, the keyframes 12 and 11 back (neighbours: they
    share map points) and 6 back (no point in common with either), best first."""

    name = "three-candidates"
    threshold = 0.5

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]:
        if keyframe.id < 12:
            return []
        return [
            LoopCandidate(keyframe.id, keyframe.id - back, 10.0 - k, {}) for k, back in enumerate((12, 11, 6))
        ]


class ScriptedVerifier:
    """Answers every candidate with ``first`` when its match is 12 keyframes back, else with an
    epipolar rejection; records which pairs it was asked about."""

    name = "scripted"

    def __init__(self, first: dict[str, object]) -> None:
        self.first = first
        self.asked: list[tuple[int, int]] = []

    def verify(self, query: Keyframe, match: Keyframe) -> Verification:
        self.asked.append((query.id, match.id))
        if query.id - match.id == 12:
            return Verification(query.id, match.id, False, "scripted", **self.first)  # type: ignore[arg-type]
        return Verification(query.id, match.id, False, "3 epipolar inliers of 40 matches")


@pytest.mark.parametrize(
    ("first", "covisible_verified"),
    [
        ({"maps_disagree": True, "inliers": 300}, False),  # the images agree, the drifted maps do not
        ({"thin_map": True, "inliers": 60}, False),  # the images agree, too few have map points
        ({"inliers": 3}, True),  # the best candidate failed as a wrong place would: try its neighbour
        # A verified loop: its neighbour may add a second constraint.
        ({"verified": True, "relative": np.eye(4), "covariance": 1e-4 * np.eye(7), "inliers": 300}, True),
    ],
)
def test_a_candidate_covisible_with_one_that_failed_on_the_maps_is_not_verified(
    loop_run: tuple[LoopClosing, list[np.ndarray], list[Keyframe]],
    first: dict[str, object],
    covisible_verified: bool,
) -> None:
    # Keyframe k observes map points 10k .. 10k + 39: neighbours share 30, keyframes 4 apart none.
    keyframes = [
        replace(k, image=None, point_ids=np.arange(10 * k.id, 10 * k.id + 40)) for k in loop_run[2][:20]
    ]
    asked, records = {}, {}
    for verify_covisible in (False, True):
        verifier = ScriptedVerifier(first)
        config = LoopClosingConfig(
            max_verifications=3, verify_covisible_candidates=verify_covisible, defer_retries=0
        )
        closing = LoopClosing(GtsamPoseGraph(BackendConfig()), ThreeCandidates(), None, verifier, config)  # type: ignore[arg-type]
        for keyframe in keyframes:
            closing.add(
                TrackResult(keyframe.frame_index, keyframe.timestamp, "tracking", keyframe.pose, 0, keyframe)
            )
        closing.finish()
        asked[verify_covisible] = set(verifier.asked)
        records[verify_covisible] = {(r.query, r.match): r for r in closing.loops()}
    queries = {q for q, _ in asked[True]}
    assert len(queries) >= 5
    # With the option on, every candidate is verified.
    assert asked[True] == {(q, q - back) for q in queries for back in (12, 11, 6)}
    # By default the neighbour of a best candidate that failed on the maps alone is not; the
    # candidate elsewhere (no shared point) always is.
    expected = {(q, q - back) for q in queries for back in ((12, 11, 6) if covisible_verified else (12, 6))}
    assert asked[False] == expected
    if not covisible_verified:
        q = min(queries)
        skipped = records[False][(q, q - 11)]
        assert not skipped.verified
        why = "maps that disagree there" if first.get("maps_disagree") else "the map thin there"
        assert (
            skipped.reason
            == f"not verified: shares 30 map points with keyframe {q - 12}, whose candidate found {why}"
        )
