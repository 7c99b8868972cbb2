"""``symbio datasets``: inspect a dataset folder the way the pipeline will read it."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from frontends.cli_common import add_json_option, print_figures, write_json
from frontends.config import load_config
from frontends.datasets import DATASET_FORMATS, SYMLINK_LOOP, open_dataset, unreachable_reason
from frontends.errors import display_path
from frontends.gt_loops import LoopLabelConfig


def input_path(text: str) -> Path:
    """An input path argument, refused when it is a symbolic link loop: ``Path.resolve()`` raises
    RuntimeError on one (Python < 3.13) where a command resolves paths before reading them. A missing
    path is left to the reader, which names it the same way."""
    path = Path(text)
    if unreachable_reason(path) == SYMLINK_LOOP:
        raise argparse.ArgumentTypeError(f"{display_path(path)}: {SYMLINK_LOOP}")
    return path


def add_dataset_arguments(parser: argparse.ArgumentParser, *, path_optional: bool = False) -> None:
    """The dataset options every command that reads a dataset takes (``path_optional``: the command
    can take the dataset from elsewhere, e.g. ``symbio run --resume``)."""
    parser.add_argument(
        "path", type=input_path, nargs="?" if path_optional else None, help="dataset folder (or video file)"
    )
    parser.add_argument(
        "--format", dest="fmt", choices=DATASET_FORMATS.names(), help="layout (default: detect)"
    )
    parser.add_argument("--calib", type=input_path, help="intrinsics YAML (overrides the dataset's own)")
    parser.add_argument("--strict", action="store_true", help="an image that fails to decode is an error")


def add_parser(subparsers: Any) -> None:
    datasets = subparsers.add_parser("datasets", help="inspect datasets").add_subparsers(
        dest="datasets_command", metavar="SUBCOMMAND", required=True
    )
    info = datasets.add_parser(
        "info",
        help="frames, duration, resolution, intrinsics, ground truth and GT loop pairs of a dataset",
        description="Print what the readers see in a dataset. GT loop pairs come from the dataset's "
        "own file when it has one, else they are computed from its GT poses (--loops-* options).",
    )
    add_dataset_arguments(info)
    info.add_argument("--loops-config", type=Path, help="YAML of LoopLabelConfig keys")
    info.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a LoopLabelConfig key (max_distance, max_angle_deg, min_time_gap)",
    )
    info.add_argument("--check-images", action="store_true", help="decode every image and count failures")
    add_json_option(info)
    info.set_defaults(handler=run_info)


def run_info(args: argparse.Namespace) -> int:
    dataset = open_dataset(args.path, args.fmt, calib=args.calib, strict=args.strict)
    figures = dataset.info(load_config(LoopLabelConfig, args.loops_config, args.overrides))
    if args.check_images:
        decoded = sum(1 for _ in dataset)
        figures["frames_decoded"] = decoded
        figures["frames_skipped"] = len(dataset.skipped)
    for note in dataset.notes:
        print(f"note: {display_path(note)}")  # notes may quote file names that are not UTF-8
    print_figures(figures)
    write_json(args.json, figures)
    return 0
