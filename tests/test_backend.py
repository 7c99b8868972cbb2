"""Self-contained tests of the pose-graph backend (slam_backend): small synthetic graphs, fast."""

from __future__ import annotations

import json
import math
from pathlib import Path

import gtsam
import numpy as np
import pytest

from frontends.config import load_config
from frontends.errors import ConfigError, InputFileError
from slam_backend.errors import PoseGraphError
from slam_backend.experiment import figures, run_problem
from slam_backend.graph_io import read_ground_truth, read_pose_graph, write_g2o
from slam_backend.lie import as_4x4
from slam_backend.posegraph import BackendConfig, GtsamPoseGraph
from slam_backend.problem import LoopCandidate, PoseGraphProblem
from slam_backend.simulate import add_false_loops

ODOMETRY_COV = np.diag([1e-6] * 3 + [1e-4] * 3 + [1e-4])
LOOP_COV = np.diag([1e-6] * 3 + [1e-4] * 3 + [1e-6])


def sim3(yaw: float, translation: tuple[float, float, float], scale: float = 1.0) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, :3] = scale * gtsam.Rot3.Rz(yaw).matrix()
    matrix[:3, 3] = translation
    return matrix


def square_loop(count: int = 40, drift: float = 0.98) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """True Sim(3) nodes on a circle whose map scale (metres per map unit) is ``drift**-k``, and the
    monocular odometry between them, which cannot see the scale change (its steps have scale 1)."""
    nodes = []
    for k in range(count):
        angle = 2 * math.pi * k / count
        position = (10 * math.cos(angle), 10 * math.sin(angle), 0.0)
        nodes.append(sim3(angle + math.pi / 2, position, drift ** (-k)))
    steps = [np.eye(4)]
    for k in range(1, count):
        step = np.linalg.inv(nodes[k - 1]) @ nodes[k]
        step[:3, :3] /= np.cbrt(np.linalg.det(step[:3, :3]))
        steps.append(step)
    return nodes, steps


def build(config: BackendConfig, steps: list[np.ndarray]) -> GtsamPoseGraph:
    graph = GtsamPoseGraph(config)
    for key, step in enumerate(steps):
        graph.add_keyframe(key, step, ODOMETRY_COV)
    return graph


def loop_between(nodes: list[np.ndarray], start: int, end: int) -> np.ndarray:
    """The exact loop measurement ``node(start)^-1 node(end)`` (sees the scale ratio)."""
    return np.linalg.inv(nodes[start]) @ nodes[end]


def positions(graph: GtsamPoseGraph) -> np.ndarray:
    return np.array([pose[:3, 3] for pose in graph.estimate().values()])


def test_sim3_loop_corrects_scale_drift() -> None:
    nodes, steps = square_loop()
    graph = build(BackendConfig(rejection="none"), steps)
    before = positions(graph)
    last = len(nodes) - 1
    decision = graph.add_loop(len(nodes) - 1, 0, loop_between(nodes, len(nodes) - 1, 0), LOOP_COV)
    assert decision.accepted
    after = positions(graph)
    closure_before = np.linalg.norm(before[-1] - before[0])
    closure_after = np.linalg.norm(after[-1] - after[0])
    true_closure = np.linalg.norm(nodes[-1][:3, 3] - nodes[0][:3, 3])
    assert closure_before > 3 * true_closure
    assert closure_after == pytest.approx(true_closure, rel=0.05)
    last_scale = np.cbrt(np.linalg.det(graph.estimate()[len(nodes) - 1][:3, :3]))
    assert last_scale == pytest.approx(0.98**-last, rel=0.05)


def test_single_false_loop_rejected_by_pcm_and_gnc() -> None:
    nodes, steps = square_loop(drift=1.0)
    for rejection in ("pcm", "pcm+gnc", "gnc"):
        graph = build(BackendConfig(rejection=rejection), steps)
        true_ids = [
            graph.add_loop(k, k + 30, loop_between(nodes, k, k + 30), LOOP_COV).loop_id for k in (2, 4, 6)
        ]
        false = graph.add_loop(9, 20, sim3(0.3, (1.0, 0.5, 0.0)), LOOP_COV)
        graph.estimate()
        decisions = graph.decisions()
        assert not decisions[false.loop_id].accepted, rejection
        assert decisions[false.loop_id].reason.split(":")[0] in ("pcm", "gnc")
        assert all(decisions[i].accepted for i in true_ids), rejection


def test_pcm_gnc_skips_the_gnc_pass_only_while_every_factor_fits() -> None:
    # True loops: every factor fits iSAM2's estimate, so no GNC pass runs at the estimates between
    # events, and the answer is the one a pass would give.
    nodes, steps = square_loop(drift=1.0)
    skipping = build(BackendConfig(), steps)
    passing = build(BackendConfig(gnc_skip_when_consistent=False), steps)
    for k in (2, 4, 6):
        for graph in (skipping, passing):
            graph.add_loop(k, k + 30, loop_between(nodes, k, k + 30), LOOP_COV)
            graph.estimate()
    assert all(d.reason.startswith("pcm") for d in skipping.decisions().values())
    assert all(d.reason.startswith("gnc") for d in passing.decisions().values())
    np.testing.assert_allclose(positions(skipping), positions(passing), atol=1e-3)
    # A lone false loop: PCM has nothing to test it against and accepts it; it bends the odometry
    # beyond its covariance, so the pass runs and rejects it.
    nodes, steps = square_loop(drift=1.0)
    graph = build(BackendConfig(), steps)
    false = graph.add_loop(9, 20, sim3(0.3, (1.0, 0.5, 0.0)), LOOP_COV)
    assert false.accepted and false.reason.startswith("pcm")
    graph.estimate()
    assert not graph.decisions()[false.loop_id].accepted
    assert graph.decisions()[false.loop_id].reason.startswith("gnc")


def test_save_load_round_trip(tmp_path: Path) -> None:
    nodes, steps = square_loop(count=20)
    graph = build(BackendConfig(rejection="pcm"), steps)
    graph.add_loop(19, 0, loop_between(nodes, 19, 0), LOOP_COV, info={"score": 0.9})
    graph.add_loop(10, 3, sim3(0.2, (0.5, 0.0, 0.0)), LOOP_COV)
    path = tmp_path / "graph.json"
    graph.save(path)
    loaded = GtsamPoseGraph.load(path)
    assert loaded.config == graph.config
    assert loaded.decisions() == graph.decisions()
    for key, pose in graph.estimate().items():
        np.testing.assert_allclose(loaded.estimate()[key], pose, atol=1e-9)
    assert json.loads(path.read_text())["loops"][0]["info"] == {"score": 0.9}


def test_load_rejects_bad_file(tmp_path: Path) -> None:
    path = tmp_path / "bad.json"
    path.write_text("{not json")
    with pytest.raises(InputFileError, match=r"bad\.json"):
        GtsamPoseGraph.load(path)


def _write_small_g2o(path: Path) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.01, 0.01, 0.01, 0.05, 0.05, 0.05]))
    truth = [
        gtsam.Pose3(gtsam.Rot3.Rz(0.5 * k), np.array([2.0 * math.cos(0.5 * k), 2.0 * math.sin(0.5 * k), 0]))
        for k in range(13)
    ]
    for k, pose in enumerate(truth):
        values.insert(k, pose)
        if k:
            graph.add(gtsam.BetweenFactorPose3(k - 1, k, truth[k - 1].between(pose), noise))
    graph.add(gtsam.BetweenFactorPose3(0, 12, truth[0].between(truth[12]), noise))
    gtsam.writeG2o(graph, values, str(path))
    return graph, values


def test_g2o_import_and_export(tmp_path: Path) -> None:
    path = tmp_path / "ring.g2o"
    _write_small_g2o(path)
    problem = read_pose_graph(path)
    assert problem.mode == "se3"
    assert len(problem.keyframe_ids) == 13 and len(problem.loops) == 1
    problem.gt_poses = read_ground_truth(path, problem.keyframe_ids)
    result = run_problem(problem, BackendConfig(mode="se3"))
    assert figures(problem, result)["ate_rmse_optimized"] < 1e-4
    graph, values = result.backend.factor_graph()
    out = tmp_path / "out.g2o"
    write_g2o(out, graph, values)
    assert len(read_pose_graph(out).loops) == 1


def test_g2o_errors_name_the_file(tmp_path: Path) -> None:
    path = tmp_path / "broken.g2o"
    path.write_text("FOO 1 2 3\n")
    with pytest.raises(InputFileError, match=r"broken\.g2o"):
        read_pose_graph(path)
    city = tmp_path / "city.txt"
    city.write_text("EDGE2 0 1 1 0 1 1 0 0\nEDGE2 1 1 2 0 1 x 0 0\n")
    with pytest.raises(InputFileError, match=r"city\.txt:2"):
        read_pose_graph(city)


def test_determinism_same_seed_same_output() -> None:
    nodes, steps = square_loop(count=30)
    loops = [
        LoopCandidate(k, k + 20, loop_between(nodes, k, k + 20), LOOP_COV, True) for k in range(0, 10, 2)
    ]
    problem = PoseGraphProblem(
        "circle",
        "sim3",
        list(range(30)),
        steps,
        [ODOMETRY_COV] * 30,
        loops,
        gt_poses=np.array([as_4x4(n) for n in nodes]),
        timestamps=np.arange(30.0),
    )
    runs = []
    for _ in range(2):
        noisy = add_false_loops(problem, 0.3, np.random.default_rng(7), min_distance=5.0)
        result = run_problem(noisy, BackendConfig())
        measured = figures(noisy, result)
        measured.pop("optimize_seconds")
        runs.append((measured, [pose.tolist() for pose in result.estimate]))
    assert runs[0] == runs[1]


def test_unknown_config_key_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="pcm_confidense"):
        load_config(BackendConfig, None, ["pcm_confidense=0.9"])
    yaml_file = tmp_path / "backend.yaml"
    yaml_file.write_text("mode: sim3\nrejection: magic\n")
    with pytest.raises(ConfigError, match=r"backend\.yaml:2"):
        load_config(BackendConfig, yaml_file)


@pytest.mark.parametrize(
    ("start", "end", "relative", "covariance", "message"),
    [
        (0, 99, np.eye(4), LOOP_COV, "not in the graph"),
        (0, 5, np.full((4, 4), np.nan), LOOP_COV, "NaN"),
        (0, 5, np.eye(4), -LOOP_COV, "not positive definite"),
        (0, 5, np.eye(4), np.eye(6), "7x7"),
        (0, 0, np.eye(4), LOOP_COV, "two different"),
    ],
)
def test_bad_loop_raises_and_leaves_graph_unchanged(
    start: int, end: int, relative: np.ndarray, covariance: np.ndarray, message: str
) -> None:
    _, steps = square_loop(count=10)
    graph = build(BackendConfig(), steps)
    graph.add_loop(9, 0, np.eye(4), LOOP_COV)
    before_estimate, before_decisions = graph.estimate(), graph.decisions()
    with pytest.raises(PoseGraphError, match=message):
        graph.add_loop(start, end, relative, covariance)
    with pytest.raises(PoseGraphError):
        graph.add_loops([(9, 1, np.eye(4), LOOP_COV, None), (start, end, relative, covariance, None)])
    assert graph.decisions() == before_decisions
    for key, pose in graph.estimate().items():
        np.testing.assert_array_equal(pose, before_estimate[key])


def test_bad_keyframe_raises_and_leaves_graph_unchanged() -> None:
    _, steps = square_loop(count=5)
    graph = build(BackendConfig(), steps)
    with pytest.raises(PoseGraphError, match="already"):
        graph.add_keyframe(4, np.eye(4), ODOMETRY_COV)
    with pytest.raises(PoseGraphError, match="positive definite"):
        graph.add_keyframe(5, np.eye(4), np.zeros((7, 7)))
    with pytest.raises(PoseGraphError, match="NaN"):
        graph.add_keyframe(5, np.full((4, 4), np.nan), ODOMETRY_COV)
    assert graph.keyframe_ids == [0, 1, 2, 3, 4]
    graph.add_keyframe(5, np.eye(4), ODOMETRY_COV)
    assert graph.keyframe_ids[-1] == 5


def test_remove_loop_restores_odometry_estimate() -> None:
    nodes, steps = square_loop(count=20)
    graph = build(BackendConfig(rejection="none"), steps)
    before = positions(graph)
    decision = graph.add_loop(19, 0, loop_between(nodes, 19, 0), LOOP_COV)
    assert not np.allclose(positions(graph), before, atol=1e-3)
    graph.remove_loop(decision.loop_id)
    np.testing.assert_allclose(positions(graph), before, atol=1e-4)
    with pytest.raises(PoseGraphError, match="does not exist"):
        graph.remove_loop(decision.loop_id)


def test_se2_and_se3_modes_share_the_api() -> None:
    for mode, size, dim in (("se3", 4, 6), ("se2", 3, 3)):
        graph = GtsamPoseGraph(BackendConfig(mode=mode))
        step = np.eye(size)
        step[0, size - 1] = 1.0
        for key in range(6):
            graph.add_keyframe(key, step if key else np.eye(size), np.eye(dim) * 1e-3)
        assert graph.add_loop(
            5, 0, np.linalg.matrix_power(np.linalg.inv(step), 5), np.eye(dim) * 1e-3
        ).accepted
        assert graph.estimate()[5][0, size - 1] == pytest.approx(5.0, abs=1e-3)
        with pytest.raises(PoseGraphError, match="scale"):
            graph.add_loop(5, 0, 2 * np.eye(size) - np.diag([0] * (size - 1) + [1]), np.eye(dim))
