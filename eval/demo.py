"""``symbio demo``: the embedded default run, needing no data from outside.

It renders a seeded synthetic loop scene (1.4 laps of a room, 20 s at 30 fps, 640x480, GT poses,
objects and loops), reads it back through the same TUM reader a user's data goes through, and runs
the whole pipeline with the default components: ``mono-vo`` frontend, ``symbiolcd2`` loop detector
with the ``oracle`` object detector (the scene's GT objects with 30 % misses: the CNN does not know
synthetic shapes), ``pycolmap`` verification and the ``gtsam`` Sim(3) pose graph with PCM + GNC.
It prints a short table and writes the same folder as ``symbio run`` (trajectories, loops.csv,
metrics.json, plots, report.html) plus the rendered scene under ``DIR/scene``, with the same
rules for DIR (see ``symbio run --help``): a folder holding files symbio did not write is refused
unless ``--overwrite``; running the demo again into its own folder replaces the earlier outputs.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from eval.components import Components
from eval.outputs import RunFolder
from frontends.cli_common import add_json_option, write_json
from frontends.config import config_to_dict, load_config
from frontends.datasets import open_dataset
from frontends.synth.world import SynthConfig
from frontends.synth.writer import write_scene

CONTACT_SHEET = "contact_sheet.png"
#: Frames of the demo scene: the synthetic default (1.4 laps at walking speed, 20 s at 30 fps).
DEMO_FRAMES = SynthConfig().frames
#: The oracle's miss rate: the paper's label matching tolerates up to 40 % missing labels.
ORACLE_MISS_RATE = 0.3
TABLE = (
    ("ATE before (m)", "ate_rmse_before", "{:.4f}"),
    ("ATE after (m)", "ate_rmse_after", "{:.4f}"),
    ("loops proposed", "loops_proposed", "{}"),
    ("loops verified", "loops_verified", "{}"),
    ("loops accepted", "loops_accepted", "{}"),
    ("false loops accepted", "false_loops_accepted", "{}"),
    ("frames / s (pipeline)", "fps", "{:.1f}"),
)


def synthetic_components() -> Components:
    """The default components with the oracle object detector at ``ORACLE_MISS_RATE``."""
    return Components(
        object_detector="oracle", overrides={"object_detector": [f"miss_rate={ORACLE_MISS_RATE}"]}
    )


def add_parser(subparsers: Any) -> None:
    demo = subparsers.add_parser(
        "demo",
        help="run the embedded default: a seeded synthetic loop scene through the whole pipeline",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    demo.add_argument("--out", type=Path, default=Path("demo_out"), help="output folder (default demo_out)")
    demo.add_argument(
        "--overwrite",
        action="store_true",
        help="write into a folder that holds other files (only the demo's own files are replaced)",
    )
    demo.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    demo.add_argument("--frames", type=int, default=DEMO_FRAMES, help=f"frames (default {DEMO_FRAMES})")
    demo.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a scene setting (see `symbio synth --help`)",
    )
    demo.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_json_option(demo)
    demo.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    overrides = [f"seed={args.seed}", f"frames={args.frames}", "trajectory=loop", *args.overrides]
    config = load_config(SynthConfig, None, overrides)
    from eval.run import run_folder  # the pipeline's libraries load once the options are checked

    folder = run_folder(
        args.out, overwrite=args.overwrite, command="symbio demo", extra_names=(CONTACT_SHEET,)
    )
    with folder:
        return _run(args, config, folder)


def _run(args: argparse.Namespace, config: SynthConfig, folder: RunFolder) -> int:
    from eval.run import build_slam, run_odometry

    scene_dir = folder.folder("scene")
    start = time.perf_counter()
    write_scene(config, scene_dir, contact_sheet=folder.path(CONTACT_SHEET), progress=not args.no_progress)
    render_seconds = time.perf_counter() - start
    dataset = open_dataset(scene_dir)
    components = synthetic_components()
    slam = build_slam(dataset, components)
    description = {
        "scene": config_to_dict(config),
        "components": {
            "frontend": components.frontend,
            "detector": components.detector,
            "object_detector": components.object_detector,
            "verifier": components.verifier,
            "backend": components.backend,
        },
        "overrides": components.overrides,
    }
    figures = run_odometry(
        dataset,
        slam,
        folder,
        progress=not args.no_progress,
        tolerance=3,
        config=description,
    )
    figures["render_seconds"] = render_seconds
    figures["seconds"] = time.perf_counter() - start
    print(f"symbio demo: synthetic loop scene (seed {args.seed}, {len(dataset)} frames) in {scene_dir}")
    print("| figure | value |\n|---|---|")
    for label, key, fmt in TABLE:
        value = figures.get(key)
        print(f"| {label} | {fmt.format(value) if value is not None else '-'} |")
    print(f"outputs: {args.out} (report.html, metrics.json, loops.csv, trajectories, plots)")
    write_json(args.json, figures)
    return 0
