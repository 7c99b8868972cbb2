"""Writing a synthetic scene to disk in the TUM RGB-D layout, plus its ground truth.

Files (all text with fixed formatting, so the same config gives byte-identical files):

* ``rgb/<timestamp>.png`` and ``rgb.txt``: images named by their 6-decimal timestamp; PNG
  compression level 1 with Huffman-only deflate (LZ77 finds little in sensor noise), encoded on a
  background thread while the next frame renders.
* ``groundtruth.txt``: TUM ``timestamp tx ty tz qx qy qz qw`` camera-to-world poses, one per frame.
* ``intrinsics.yaml``: ``fx fy cx cy width height distortion``.
* ``gt_objects.jsonl``: per frame, the objects with at least ``min_visible_pixels`` visible pixels.
* ``scene.json``: the config, the path figures, the loop-label config and every world object.
* ``gt_loop_pairs.txt``: ``query ref`` frame pairs whose rendered views overlap
  (``frontends.synth.covisibility`` with ``config.loop_labels``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
import zlib
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import yaml
from evo.core.trajectory import PoseTrajectory3D
from tqdm import tqdm

from frontends.config import config_to_dict
from frontends.errors import ConfigError, InputFileError
from frontends.gt_loops import write_loop_pairs
from frontends.synth.covisibility import covisible_pairs
from frontends.synth.render import GtObject, RenderedFrame, SceneRenderer
from frontends.synth.world import BAYS_FIELDS, SynthConfig, WorldObject
from frontends.trajectory_io import write_trajectory

#: Level 1 Huffman-only deflate: on noisy images it is ~2x faster than level 1 and ~10 % smaller.
PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
CONTACT_SHEET_FRAMES = 16
CONTACT_SHEET_COLUMNS = 4
#: Frames encoded ahead of the renderer at most (bounds memory).
MAX_PENDING_WRITES = 8


def write_scene(
    config: SynthConfig, out_dir: str | Path, progress: bool = True, contact_sheet: str | Path | None = None
) -> dict[str, float | int]:
    """Render ``config`` into ``out_dir``; returns the figures the CLI prints."""
    out = Path(out_dir)
    _prepare_output(out)
    start = time.perf_counter()
    scene = SceneRenderer(config)
    setup_seconds = time.perf_counter() - start
    names = [f"{t:.6f}.png" for t in scene.path.timestamps]
    sheet_frames = set(np.linspace(0, config.frames - 1, CONTACT_SHEET_FRAMES).round().astype(int).tolist())
    thumbnails: list[np.ndarray] = []
    object_lines: list[str] = []
    static_per_frame: list[int] = []
    depth_grids: list[np.ndarray] = []
    render_seconds = 0.0
    pending: deque[tuple[Path, Future[bool]]] = deque()
    loop_start = time.perf_counter()
    with (
        ThreadPoolExecutor(max_workers=1) as pool,
        tqdm(total=config.frames, disable=not progress, unit="frame", desc="synth") as bar,
    ):
        for index in range(config.frames):
            tick = time.perf_counter()
            frame = scene.frame(index)
            depth_grids.append(scene.depth_samples(config.loop_labels.depth_step))
            render_seconds += time.perf_counter() - tick
            path = out / "rgb" / names[index]
            pending.append((path, pool.submit(cv2.imwrite, str(path), frame.image, PNG_PARAMS)))
            while len(pending) > MAX_PENDING_WRITES:
                _finish(*pending.popleft())
            object_lines.append(_objects_line(frame))
            static_per_frame.append(sum(not obj.movable for obj in frame.objects))
            if contact_sheet is not None and index in sheet_frames:
                thumbnails.append(_thumbnail(frame))
            bar.update()
        while pending:
            _finish(*pending.popleft())
    loop_seconds = time.perf_counter() - loop_start

    header = [
        "# color images",
        f"# file: 'synth_{config.trajectory}_seed{config.seed}'",
        "# timestamp filename",
    ]
    rows = [f"{t:.6f} rgb/{name}" for t, name in zip(scene.path.timestamps, names, strict=True)]
    (out / "rgb.txt").write_text("\n".join(header + rows) + "\n", encoding="utf-8")
    trajectory = PoseTrajectory3D(poses_se3=list(scene.path.poses), timestamps=scene.path.timestamps)
    write_trajectory(out / "groundtruth.txt", trajectory, "tum")
    intrinsics = config.intrinsics.as_dict()
    (out / "intrinsics.yaml").write_text(yaml.safe_dump(intrinsics, sort_keys=False), encoding="utf-8")
    (out / "gt_objects.jsonl").write_text("".join(line + "\n" for line in object_lines), encoding="utf-8")
    label_start = time.perf_counter()
    pairs = covisible_pairs(
        np.stack(depth_grids), scene.path.poses, scene.path.timestamps, config.intrinsics, config.loop_labels
    )
    label_seconds = time.perf_counter() - label_start
    write_loop_pairs(out / "gt_loop_pairs.txt", pairs)
    path_figures = {
        "scale": round(scene.path.scale, 4),
        "length_m": round(scene.path.length, 4),
        "mean_speed_mps": round(scene.path.mean_speed, 4),
        "max_rotation_deg_per_frame": round(scene.path.max_rotation_deg, 4),
    }
    description = {
        "config": config_record(config),
        "intrinsics": intrinsics,
        "loop_labels": dataclasses.asdict(config.loop_labels),
        "path": path_figures,
        "room_size": list(scene.world.room_size),
        "objects": [_object_record(obj) for obj in scene.world.objects],
    }
    (out / "scene.json").write_text(json.dumps(description, indent=2) + "\n", encoding="utf-8")
    if contact_sheet is not None:
        _write_image(Path(contact_sheet), _contact_sheet(thumbnails))
    movable = sum(obj.movable for obj in scene.world.objects)
    return {
        "frames": config.frames,
        "gt_loop_pairs": len(pairs),
        "loop_query_frames": len(np.unique(pairs[:, 0])),
        "objects": len(scene.world.objects) - movable,
        "movable_objects": movable,
        "objects_per_frame_mean": round(float(np.mean(static_per_frame)), 3),
        "mean_speed_mps": path_figures["mean_speed_mps"],
        "max_rotation_deg_per_frame": path_figures["max_rotation_deg_per_frame"],
        "render_fps": config.frames / render_seconds,
        "write_fps": config.frames / loop_seconds,
        "setup_seconds": setup_seconds,
        "label_seconds": label_seconds,
        "seconds": time.perf_counter() - start,
    }


def cached_scene(config: SynthConfig, folder: str | Path) -> Path:
    """``folder`` holding ``config``'s scene: rendered unless a complete render of the same config
    (its ``scene.json``, written last) is already there, so a changed config or labeller re-renders."""
    folder = Path(folder)
    try:
        current = json.loads((folder / "scene.json").read_text(encoding="utf-8"))["config"]
    except (OSError, ValueError, KeyError):
        current = None
    if current != json.loads(json.dumps(config_record(config))):
        write_scene(config, folder, progress=False)
    return folder


def config_record(config: SynthConfig) -> dict[str, object]:
    """The config as ``scene.json`` stores it; a room scene leaves out the bays-layout fields that hold
    their defaults, so it keeps the files (and cache keys) it had before those fields existed."""
    record = config_to_dict(config)
    if config.layout == "room":
        defaults = config_to_dict(SynthConfig())
        for name in BAYS_FIELDS:
            if record[name] == defaults[name]:
                del record[name]
    return record


def _prepare_output(out: Path) -> None:
    """Create ``out/rgb``; refuse a non-empty folder that is not an earlier synthetic scene."""
    if out.exists() and any(out.iterdir()) and not (out / "scene.json").is_file():
        raise ConfigError(
            f"{out}: folder is not empty and holds no synthetic scene; choose a new --out folder"
        )
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    # Images of an earlier, longer scene would otherwise stay next to the new ones.
    for stale in (out / "rgb").glob("*.png"):
        stale.unlink()


def _finish(path: Path, future: Future[bool]) -> None:
    if not future.result():
        raise InputFileError(path, "cannot write image")


def _write_image(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), image):
        raise InputFileError(path, "cannot write image")


def _objects_line(frame: RenderedFrame) -> str:
    objects = [
        {
            "label": obj.label,
            "instance": obj.instance,
            "box": list(obj.box),
            "visible_fraction": round(obj.visible_fraction, 4),
            "movable": obj.movable,
        }
        for obj in frame.objects
    ]
    return json.dumps({"frame": frame.index, "timestamp": round(frame.timestamp, 6), "objects": objects})


def _object_record(obj: WorldObject) -> dict[str, object]:
    record: dict[str, object] = {
        "label": obj.label,
        "instance": obj.instance,
        "centre": [round(v, 4) for v in obj.centre],
        "size": list(obj.size),
        "yaw": round(obj.yaw, 6),
        "movable": obj.movable,
    }
    if obj.movable:
        record["motion"] = {
            "amplitude": round(obj.amplitude, 4),
            "period": round(obj.period, 4),
            "phase": round(obj.phase, 4),
            "axis": "local x",
        }
    return record


def label_colour(label: str) -> tuple[int, int, int]:
    """A stable BGR colour per class label."""
    hue = zlib.crc32(label.encode("utf-8")) % 180
    bgr = cv2.cvtColor(np.array([[[hue, 220, 255]]], np.uint8), cv2.COLOR_HSV2BGR)[0, 0]
    return int(bgr[0]), int(bgr[1]), int(bgr[2])


def _thumbnail(frame: RenderedFrame) -> np.ndarray:
    """A half-size copy of the frame with its ground-truth boxes and labels drawn."""
    thumb = cv2.resize(frame.image, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    for obj in frame.objects:
        _draw_box(thumb, obj)
    cv2.putText(
        thumb,
        f"#{frame.index}  t={frame.timestamp:.2f}",
        (4, 14),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.4,
        (255, 255, 255),
        1,
        cv2.LINE_AA,
    )
    return thumb


def _draw_box(thumb: np.ndarray, obj: GtObject) -> None:
    # Movable objects: thick red boxes, so what a detector must drop stands out.
    colour = (0, 0, 255) if obj.movable else label_colour(obj.label)
    x0, y0, x1, y1 = (v // 2 for v in obj.box)
    cv2.rectangle(thumb, (x0, y0), (max(x0, x1 - 1), max(y0, y1 - 1)), colour, 2 if obj.movable else 1)
    text = f"{obj.label} {obj.instance}"
    cv2.putText(
        thumb, text, (x0 + 2, max(10, y0 + 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.33, colour, 1, cv2.LINE_AA
    )


def _contact_sheet(thumbnails: list[np.ndarray]) -> np.ndarray:
    rows = math.ceil(len(thumbnails) / CONTACT_SHEET_COLUMNS)
    height, width = thumbnails[0].shape[:2]
    sheet = np.zeros((rows * height, CONTACT_SHEET_COLUMNS * width, 3), np.uint8)
    for k, thumb in enumerate(thumbnails):
        r, c = divmod(k, CONTACT_SHEET_COLUMNS)
        sheet[r * height : (r + 1) * height, c * width : (c + 1) * width] = thumb
    return sheet
