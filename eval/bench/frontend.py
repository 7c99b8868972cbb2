"""Benchmark of the ``mono-vo`` frontend: speed against bare ORB extraction, and accuracy.

For each input, in one run: frames per second of the frontend's own ORB extractor alone on the
frames (held in memory, so decoding is not timed), then of the whole frontend on the same frames,
fed as ``symbio run`` feeds it (``with_lookahead``: each frame's ORB runs on a worker thread while
the previous frame is tracked), their ratio, the per-stage milliseconds per frame ("orb" = the wait
for the features), and the accuracy: evo APE (translation RMSE)
after Sim(3) Umeyama alignment of every posed frame of segment 0 (keyframes with their
bundle-adjusted poses), relative to the ground-truth path length.

Inputs: a synthetic 640x480 scene rendered in memory with ``frontends.synth`` (``--trajectory``,
``--seed``, ``--frames``), and the KITTI 06 clip (1226x370) when the shared data exists
(``SYMBIO_SHARED``, default ../shared). ``--scenes loop:21,figure8:22`` adds accuracy-only rows of
further synthetic scenes; ``--mask-movable 0.3`` masks their walking people on keyframes as the
pipeline does with its object detector (GT boxes, each missed with that probability).

Usage: ``python -m eval.bench.frontend [--frames 300] [--scenes ...] [--set key=value] [--json OUT]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from evo.core import metrics
from evo.core.trajectory import PoseTrajectory3D

from eval.bench.scenes import scene_frames
from frontends.base import Frontend, TrackResult, with_lookahead
from frontends.cli_common import add_json_option, write_json
from frontends.datasets import open_dataset
from frontends.mono_vo import create
from frontends.mono_vo.features import OrbExtractor
from frontends.types import CameraIntrinsics, Frame

KITTI_CLIP = Path("data/clips/kitti06_f000-050")


def synthetic_frames(trajectory: str, seed: int, frames: int) -> tuple[CameraIntrinsics, list[Frame]]:
    """A synthetic scene rendered in memory (no disk), with ground-truth poses."""
    camera, result, _ = scene_frames(trajectory, seed, frames)
    return camera, result


def oracle_masks(
    movable: Sequence[Sequence[tuple[int, int, int, int]]], miss_rate: float, seed: int
) -> Callable[[Frame], list[tuple[int, int, int, int]]]:
    """The movable objects' boxes of a frame, each missed with ``miss_rate`` (seeded per frame), as
    the pipeline's ``oracle`` object detector gives them to the frontend for masking."""

    def boxes(frame: Frame) -> list[tuple[int, int, int, int]]:
        draws = np.random.default_rng([seed, frame.index]).random(len(movable[frame.index]))
        return [box for box, draw in zip(movable[frame.index], draws, strict=True) if draw >= miss_rate]

    return boxes


def dataset_frames(path: Path, fmt: str | None) -> tuple[CameraIntrinsics, list[Frame]]:
    dataset = open_dataset(path, fmt)
    return dataset.camera, list(dataset)


def track_all(frontend: Frontend, frames: Sequence[Frame]) -> dict[int, TrackResult]:
    """Each frame's result, fed as ``symbio run`` feeds them; a frame posed late (backfilled after a
    relocalisation) has its late result."""
    results: dict[int, TrackResult] = {}
    for frame in with_lookahead(frames, frontend):
        result = frontend.track(frame)
        results[frame.index] = result
        results.update((late.frame_index, late) for late in result.backfilled)
    return results


def evaluate(
    camera: CameraIntrinsics,
    frames: Sequence[Frame],
    overrides: Sequence[str] = (),
    dynamic_objects: Callable[[Frame], Sequence[Sequence[float]]] | None = None,
) -> dict[str, Any]:
    """Run the frontend over ``frames`` (masking ``dynamic_objects(frame)`` on keyframes, if given);
    speed, per-stage times, tracking states and ATE."""
    frontend = create(camera, overrides)
    frontend.set_dynamic_objects(dynamic_objects)
    start = time.perf_counter()
    results = track_all(frontend, frames)
    seconds = time.perf_counter() - start
    states = Counter(r.state for r in results.values())
    poses = {i: r.pose for i, r in results.items() if r.pose is not None}
    segments = {i: r.segment for i, r in results.items() if r.pose is not None}
    keyframes = frontend.keyframes()
    for keyframe in keyframes:
        poses[keyframe.frame_index] = keyframe.pose
        segments[keyframe.frame_index] = keyframe.segment
    figures: dict[str, Any] = {
        "frames": len(frames),
        "fps": len(frames) / seconds,
        "posed_frames": len(poses),
        "keyframes": len(keyframes),
        "segments": len(set(segments.values())),
        **{f"frames_{state}": count for state, count in sorted(states.items())},
        **{f"ms_{stage}": 1000 * s / len(frames) for stage, s in sorted(frontend.stage_seconds.items())},
    }
    figures.update(ate(frames, poses, segments))
    return figures


def ate(frames: Sequence[Frame], poses: dict[int, np.ndarray], segments: dict[int, int]) -> dict[str, float]:
    """evo APE (translation RMSE) of segment 0 after Sim(3) alignment, and the GT path length."""
    by_index = {f.index: f for f in frames}
    gt_all = [f for f in frames if f.gt_pose is not None]
    if len(gt_all) < 2:
        return {}
    path = PoseTrajectory3D(
        poses_se3=[f.gt_pose for f in gt_all], timestamps=np.array([f.timestamp for f in gt_all])
    ).path_length
    indices = [i for i in sorted(poses) if segments[i] == 0 and by_index[i].gt_pose is not None]
    if len(indices) < 3:
        return {"gt_path_length": path}
    stamps = np.array([by_index[i].timestamp for i in indices])
    estimate = PoseTrajectory3D(poses_se3=[poses[i] for i in indices], timestamps=stamps)
    reference = PoseTrajectory3D(poses_se3=[by_index[i].gt_pose for i in indices], timestamps=stamps)
    estimate.align(reference, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((reference, estimate))
    rmse = float(ape.get_statistic(metrics.StatisticsType.rmse))
    return {
        "ate": rmse,
        "gt_path_length": path,
        "ate_percent_of_path": 100 * rmse / path,
        "ate_frames": len(indices),
    }


def orb_fps(camera: CameraIntrinsics, frames: Sequence[Frame], overrides: Sequence[str] = ()) -> float:
    """Frames per second of the frontend's ORB extractor alone."""
    extractor = OrbExtractor(create(camera, overrides).config.orb, camera)
    grays = [f.gray for f in frames]
    start = time.perf_counter()
    for gray in grays:
        extractor.extract(gray)
    return len(grays) / (time.perf_counter() - start)


def bench_input(
    name: str, camera: CameraIntrinsics, frames: list[Frame], overrides: Sequence[str]
) -> dict[str, Any]:
    orb = orb_fps(camera, frames, overrides)
    figures = evaluate(camera, frames, overrides)
    figures["orb_fps"] = orb
    figures["ratio_to_orb"] = figures["fps"] / orb
    figures["resolution"] = f"{camera.width}x{camera.height}"
    return {f"{name}_{key}": value for key, value in figures.items()}


def print_table(rows: dict[str, dict[str, Any]]) -> None:
    columns = [
        ("resolution", "{}"), ("fps", "{:.1f}"), ("orb_fps", "{:.1f}"), ("ratio_to_orb", "{:.2f}"),
        ("posed_frames", "{}"), ("frames", "{}"), ("keyframes", "{}"), ("segments", "{}"),
        ("ate", "{:.4f}"), ("ate_percent_of_path", "{:.3f}"),
    ]  # fmt: skip
    print("| input | " + " | ".join(c for c, _ in columns) + " |")
    print("|---" * (len(columns) + 1) + "|")
    for name, figures in rows.items():
        cells = [fmt.format(figures[c]) if c in figures else "-" for c, fmt in columns]
        print(f"| {name} | " + " | ".join(cells) + " |")
    print()
    for name, figures in rows.items():
        stages = {k[3:]: v for k, v in figures.items() if k.startswith("ms_")}
        print(f"{name} ms/frame: " + ", ".join(f"{k} {v:.1f}" for k, v in stages.items()))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=300, help="frames of the 640x480 speed scene")
    parser.add_argument("--trajectory", default="loop")
    parser.add_argument("--seed", type=int, default=21)
    parser.add_argument("--scenes", default="", help="extra synthetic scenes for accuracy: kind:seed,...")
    parser.add_argument("--scene-frames", type=int, default=600)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="frontend override")
    parser.add_argument(
        "--mask-movable",
        type=float,
        metavar="MISS_RATE",
        help="--scenes rows: mask the walking people's GT boxes on keyframes, each missed with this "
        "probability (0.3: as the pipeline's oracle detector)",
    )
    add_json_option(parser)
    args = parser.parse_args(argv)

    rows: dict[str, dict[str, Any]] = {}
    camera, frames = synthetic_frames(args.trajectory, args.seed, args.frames)
    rows[f"synth_{args.trajectory}_{args.seed}"] = bench_input("x", camera, frames, args.set)
    shared = Path(os.environ.get("SYMBIO_SHARED", Path(__file__).resolve().parents[2].parent / "shared"))
    if (shared / KITTI_CLIP).is_dir():
        camera, frames = dataset_frames(shared / KITTI_CLIP, "kitti")
        rows["kitti06_f000-050"] = bench_input("x", camera, frames, args.set)
    for item in filter(None, args.scenes.split(",")):
        kind, _, seed = item.partition(":")
        scene_seed = int(seed or 0)
        camera, frames, movable = scene_frames(kind, scene_seed, args.scene_frames)
        masks = None if args.mask_movable is None else oracle_masks(movable, args.mask_movable, scene_seed)
        figures = evaluate(camera, frames, args.set, masks)
        rows[f"synth_{kind}_{seed}"] = {f"x_{k}": v for k, v in figures.items()}
    rows = {name: {k[2:]: v for k, v in figures.items()} for name, figures in rows.items()}
    print_table(rows)
    if args.json:
        flat = {f"{name}_{key}": value for name, figures in rows.items() for key, value in figures.items()}
        write_json(args.json, flat)
    return 0


if __name__ == "__main__":
    sys.exit(main())
