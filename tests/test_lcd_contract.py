"""Every registered detector keeps the Protocol contract; `symbio eval lcd` survives failing plugins."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from eval.cli import main as symbio_main
from eval.lcd_eval import run_lcd
from frontends.datasets import open_dataset
from frontends.errors import SymbioError
from frontends.orb import OrbConfig, extract_orb
from frontends.types import DetectedObject, Frame, Keyframe
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS, LoopCandidate, LoopDetector, ObjectDetector


@pytest.fixture(scope="module")
def keyframes(small_loop_scene: Path) -> list[Keyframe]:
    """Every 10th frame of the small loop scene with GT objects, plus a featureless black frame."""
    dataset = open_dataset(small_loop_scene)
    oracle = OBJECT_DETECTORS.load("oracle")()
    out: list[Keyframe] = []
    for frame in (f for f in dataset if f.index % 10 == 0):
        keypoints, descriptors = extract_orb(frame.gray)
        objects = tuple(oracle.detect(frame.image, frame))
        out.append(
            Keyframe(
                len(out),
                frame.index,
                frame.timestamp,
                np.eye(4),
                keypoints,
                descriptors,
                objects,
                frame.image,
            )
        )
    black = np.zeros_like(out[0].image)
    keypoints, descriptors = extract_orb(black[..., 0])
    out.insert(5, Keyframe(5, -1, -1.0, np.eye(4), keypoints, descriptors, (), black))
    return [
        Keyframe(i, k.frame_index, k.timestamp, k.pose, k.keypoints, k.descriptors, k.objects, k.image)
        for i, k in enumerate(out)
    ]


@pytest.mark.parametrize("name", LOOP_DETECTORS.names())
def test_loop_detector_contract(name: str, keyframes: list[Keyframe]) -> None:
    detector = LOOP_DETECTORS.load(name)()
    assert isinstance(detector, LoopDetector) and isinstance(detector.threshold, float)
    window = int(getattr(detector, "temporal_window", 0))
    answered = 0
    for keyframe in keyframes:
        candidates = detector.add(keyframe)
        assert isinstance(candidates, list)
        assert [c.score for c in candidates] == sorted((c.score for c in candidates), reverse=True)
        for candidate in candidates:
            assert isinstance(candidate, LoopCandidate) and candidate.query == keyframe.id
            assert 0 <= candidate.match < keyframe.id - window  # earlier and outside the window
            assert candidate.match != 5  # the featureless keyframe is never proposed
            assert np.isfinite(candidate.score)
            assert all(isinstance(v, float) for v in candidate.components.values())
        answered += bool(candidates)
        if keyframe.id == 5:
            assert candidates == []
    assert answered > 0


@pytest.mark.parametrize("name", OBJECT_DETECTORS.names())
def test_object_detector_contract(name: str, small_loop_scene: Path) -> None:
    try:
        detector = OBJECT_DETECTORS.load(name)()
    except SymbioError as exc:  # needs a model file: the error must say which setting
        assert "model" in str(exc)
        return
    assert isinstance(detector, ObjectDetector)
    frame = next(iter(open_dataset(small_loop_scene)))
    for image in (frame.image, np.zeros_like(frame.image)):
        objects = detector.detect(image, frame)
        assert isinstance(objects, list) and all(isinstance(o, DetectedObject) for o in objects)
        for obj in objects:
            x0, y0, x1, y1 = obj.box
            assert 0 <= obj.score <= 1 and x0 < x1 and y0 < y1


class _FlakyDetector:
    """Raises on every third keyframe, otherwise proposes the oldest eligible keyframe."""

    name, threshold, temporal_window = "flaky", 0.5, 2

    def __init__(self) -> None:
        self.seen = 0

    def add(self, keyframe: Keyframe) -> list[LoopCandidate]:
        self.seen += 1
        if keyframe.id % 3 == 2:
            raise RuntimeError("boom")
        return [LoopCandidate(keyframe.id, 0, 1.0)] if keyframe.id > 2 else []


class _BrokenObjects:
    name = "broken"

    def detect(self, image: np.ndarray, frame: Frame | None = None) -> list[DetectedObject]:
        raise ValueError("no objects today")


def test_failing_plugins_cost_single_queries(
    small_loop_scene: Path, caplog: pytest.LogCaptureFixture
) -> None:
    dataset = open_dataset(small_loop_scene)
    detector = _FlakyDetector()
    (run,) = run_lcd(dataset, [detector], _BrokenObjects(), OrbConfig(), 0.5, 0, progress=False)
    assert run.keyframes == detector.seen == len(run.records) > 6
    assert run.loop_detector_failures == len([r for r in run.records if r.keyframe % 3 == 2])
    assert run.object_failures == run.keyframes
    assert all(r.score == float("-inf") for r in run.records if r.keyframe % 3 == 2)
    assert any(r.score == 1.0 for r in run.records)
    assert "loop detector flaky failed on keyframe 2" in caplog.text and "rgb/" in caplog.text


def test_eval_lcd_cli(small_loop_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "s.json"
    code = symbio_main(
        ["eval", "lcd", str(small_loop_scene), "--detector", "symbiolcd2", "--tolerance", "5",
         "--no-progress", "--object-set", "miss_rate=0.3", "--json", str(out),
         "--csv", str(tmp_path / "q.csv"), "--plot", str(tmp_path / "pr.png")]
    )  # fmt: skip
    assert code == 0
    figures = json.loads(out.read_text())
    assert figures["object_detector"] == "oracle" and figures["loop_detector_failures"] == 0
    assert 0 <= figures["object_poor_keyframes"] < figures["keyframes"]
    for key in ("precision", "recall", "recall_at_100p", "auc_pr", "ms_per_keyframe_p50", "ms_objects_p95"):
        assert key in figures
    assert figures["queries_with_loop"] > 5 and figures["recall_at_100p"] > 0.5
    assert (tmp_path / "pr.png").stat().st_size > 0
    assert len((tmp_path / "q.csv").read_text().splitlines()) == figures["queries"] + 1
    assert "recall_at_100p" in capsys.readouterr().out


@pytest.mark.slow
def test_eval_lcd_compares_detectors_on_one_pass(
    small_loop_scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "c.json"
    names = "vbow,symbiolcd2-flat,symbiolcd2"
    args = ["eval", "lcd", str(small_loop_scene), "--detector", names, "--keyframe-period", "0.5"]
    assert symbio_main([*args, "--no-progress", "--json", str(out), "--csv", str(tmp_path / "q.csv")]) == 0
    table = capsys.readouterr().out
    assert all(f"| {name} |" in table for name in names.split(","))
    figures = json.loads(out.read_text())
    assert {figures[f"{name}.queries"] for name in names.split(",")} == {figures["vbow.keyframes"]}
    rows = (tmp_path / "q.csv").read_text().splitlines()
    assert len(rows) == 1 + 3 * figures["vbow.queries"]
    assert symbio_main(["eval", "lcd", str(small_loop_scene), "--detector", "vbow,vbow"]) == 2
    assert "distinct detector names" in capsys.readouterr().err
