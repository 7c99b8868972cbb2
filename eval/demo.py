"""``symbio demo``: the embedded default run, needing no data from outside.

It renders a seeded synthetic loop scene, reads it back through the same TUM reader a user's data
goes through, and prints the figures of every stage that exists so far. Later stages (visual
odometry, SymbioLCD2, the pose graph) extend this command as they land; it stays the one command
that shows the whole tool working on a fresh machine.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.config import load_config
from frontends.datasets import open_dataset
from frontends.synth.world import SynthConfig
from frontends.synth.writer import write_scene

#: Frames of the demo scene: 1.4 laps of the room at walking speed.
DEMO_FRAMES = 300
#: ORB is measured on every n-th frame only: it reports the scene's texture, not a frontend.
ORB_SAMPLE_EVERY = 10


def add_parser(subparsers: Any) -> None:
    demo = subparsers.add_parser(
        "demo",
        help="run the embedded default: a seeded synthetic loop scene through every built stage",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    demo.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default demo_out)")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--frames", type=int, default=DEMO_FRAMES)
    demo.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a scene setting (see `symbio synth --help`)",
    )
    add_json_option(demo)
    demo.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    overrides = [f"seed={args.seed}", f"frames={args.frames}", "trajectory=loop", *args.overrides]
    config = load_config(SynthConfig, None, overrides)
    scene_dir = args.out / "scene"
    start = time.perf_counter()
    synth_figures = write_scene(config, scene_dir, contact_sheet=args.out / "contact_sheet.png")
    dataset = open_dataset(scene_dir)
    orb = cv2.ORB.create(nfeatures=1500)
    features = [len(orb.detect(frame.gray, None)) for frame in dataset if frame.index % ORB_SAMPLE_EVERY == 0]
    info = dataset.info()
    figures: dict[str, Any] = {
        "frames": info["frames"],
        "duration_s": info["duration"],
        "resolution": f"{info['width']}x{info['height']}",
        "gt_poses": info["gt_poses"],
        "gt_loop_pairs": info["gt_loop_pairs"],
        "gt_loop_queries": info["gt_loop_queries"],
        "render_fps": synth_figures["render_fps"],
        "orb_features_per_frame": float(np.mean(features)),
        "frames_skipped": len(dataset.skipped),
        "seconds": time.perf_counter() - start,
    }
    print(f"symbio demo: synthetic loop scene (seed {args.seed}) in {scene_dir}")
    print_figures(figures)
    print(f"  contact sheet: {args.out / 'contact_sheet.png'}")
    (args.out / "metrics.json").write_text(
        json.dumps(figures, indent=2, sort_keys=True) + "\n", encoding="utf-8"
    )
    write_json(args.json, figures)
    return 0
