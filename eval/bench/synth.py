"""Benchmark of the synthetic scene generator on one core.

For each trajectory kind: scene setup time (textures, noise bank), render-only frames per second
(``SceneRenderer.frame``: rasterising, sensor effects and ground-truth boxes) and render+write frames
per second (``write_scene`` into a temporary folder, PNG encoding included). OpenCV is limited to
one thread and, where the OS allows, the process is pinned to one CPU, so the PNG writer thread
shares that core. Target: >= 30 render fps at 640x480.

Usage: ``python -m eval.bench.synth [--frames 150] [--json OUT]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import cv2

from frontends.cli_common import add_json_option, write_json
from frontends.synth.render import SceneRenderer
from frontends.synth.world import TRAJECTORY_KINDS, SynthConfig
from frontends.synth.writer import write_scene


def pin_to_one_core() -> str:
    """Limit OpenCV to one thread and the process to one CPU; returns what was done."""
    cv2.setNumThreads(1)
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"pinned to CPU {cpu}, cv2 threads 1"
    return "cv2 threads 1 (CPU pinning unavailable)"


def bench(frames: int, seed: int = 0) -> dict[str, float]:
    figures: dict[str, float] = {}
    total_frames, render_seconds, write_seconds = 0, 0.0, 0.0
    for kind in TRAJECTORY_KINDS:
        config = SynthConfig(trajectory=kind, frames=frames, seed=seed)
        start = time.perf_counter()
        scene = SceneRenderer(config)
        setup = time.perf_counter() - start
        start = time.perf_counter()
        for index in range(frames):
            scene.frame(index)
        rendered = time.perf_counter() - start
        with tempfile.TemporaryDirectory() as folder:
            written = write_scene(config, Path(folder) / "scene", progress=False)
        loop = frames / float(written["write_fps"])
        figures[f"setup_seconds_{kind}"] = setup
        figures[f"render_fps_{kind}"] = frames / rendered
        figures[f"render_write_fps_{kind}"] = frames / loop
        total_frames += frames
        render_seconds += rendered
        write_seconds += loop
    figures["render_fps"] = total_frames / render_seconds
    figures["render_write_fps"] = total_frames / write_seconds
    figures["frames_per_trajectory"] = frames
    return figures


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=150, help="frames per trajectory kind (default 150)")
    parser.add_argument("--seed", type=int, default=0)
    add_json_option(parser)
    args = parser.parse_args(argv)
    setting = pin_to_one_core()
    figures = bench(args.frames, args.seed)
    print(f"synthetic scenes, {args.frames} frames of 640x480 per trajectory ({setting})\n")
    print("| trajectory | setup s | render fps | render+write fps |")
    print("|---|---:|---:|---:|")
    for kind in TRAJECTORY_KINDS:
        print(
            f"| {kind} | {figures[f'setup_seconds_{kind}']:.2f} | {figures[f'render_fps_{kind}']:.1f} "
            f"| {figures[f'render_write_fps_{kind}']:.1f} |"
        )
    print(f"| **all** | | **{figures['render_fps']:.1f}** | **{figures['render_write_fps']:.1f}** |")
    write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
