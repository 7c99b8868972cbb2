"""``symbio synth``: write a deterministic synthetic multi-object loop scene in the TUM RGB-D layout."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.config import load_config
from frontends.synth.world import LAYOUTS, TRAJECTORY_KINDS, SynthConfig


def add_parser(subparsers: Any) -> None:
    parser: argparse.ArgumentParser = subparsers.add_parser(
        "synth",
        help="render a synthetic room scene with objects and ground-truth loops",
        description="Render a deterministic synthetic room (textured walls, COCO-labelled objects, walking "
        "people) seen along a camera path, in the TUM RGB-D layout with ground-truth poses, object boxes "
        "and loop pairs. The same config and seed give byte-identical files.",
    )
    parser.add_argument(
        "--trajectory", choices=TRAJECTORY_KINDS, help="camera path (default: loop; hall for --layout bays)"
    )
    parser.add_argument(
        "--layout",
        choices=LAYOUTS,
        help="one room (default), or a hall of identically textured bays with different objects",
    )
    parser.add_argument("--seed", type=int, help="random seed of the whole scene (default: 0)")
    parser.add_argument("--frames", type=int, help="number of frames (default: 600, 20 s at 30 fps)")
    parser.add_argument("--out", type=Path, required=True, help="output folder (created)")
    parser.add_argument(
        "--contact-sheet",
        type=Path,
        metavar="PNG",
        help="also save a grid of 16 frames with their ground-truth boxes",
    )
    parser.add_argument("--config", type=Path, metavar="YAML", help="SynthConfig values to apply first")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one SynthConfig value (repeatable), e.g. --set noise_sigma=3",
    )
    parser.add_argument("--no-progress", action="store_true", help="do not show a progress bar")
    add_json_option(parser)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from frontends.synth.writer import write_scene

    overrides = list(args.overrides)
    # Explicit flags win over --config and --set.
    for key in ("layout", "trajectory", "seed", "frames"):
        value = getattr(args, key)
        if value is not None:
            overrides.append(f"{key}={value}")
    config = load_config(SynthConfig, args.config, overrides)
    figures = write_scene(config, args.out, progress=not args.no_progress, contact_sheet=args.contact_sheet)
    print(f"synth: wrote a {config.layout} {config.trajectory} scene (seed {config.seed}) to {args.out}")
    print_figures(figures)
    if args.contact_sheet is not None:
        print(f"  contact sheet: {args.contact_sheet}")
    write_json(args.json, figures)
    return 0
