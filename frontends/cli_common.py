"""Helpers shared by the ``symbio`` subcommands of every package."""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any


def add_json_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--json", metavar="PATH", type=Path, help="write the measured figures as a flat JSON object"
    )


def add_set_option(parser: argparse.ArgumentParser, help: str) -> None:
    """``--set KEY=VALUE`` (repeatable) into ``args.overrides``."""
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help=help
    )


def write_json(path: str | Path | None, figures: Mapping[str, Any]) -> None:
    """Write a flat JSON object of scalar figures (NaN/inf become null, numpy scalars plain numbers)."""
    if path is None:
        return
    flat: dict[str, Any] = {}
    for key, value in figures.items():
        if hasattr(value, "item") and callable(value.item):
            value = value.item()
        if isinstance(value, float) and not math.isfinite(value):
            value = None
        if isinstance(value, (Mapping, list, tuple)):
            raise TypeError(f"--json output must be flat; {key!r} is a {type(value).__name__}")
        flat[key] = value
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(json.dumps(flat, indent=2, sort_keys=True) + "\n", encoding="utf-8")


def print_figures(figures: Mapping[str, Any]) -> None:
    """Print figures as an aligned two-column table."""
    width = max((len(k) for k in figures), default=0)
    for key, value in figures.items():
        shown = f"{value:.4g}" if isinstance(value, float) else str(value)
        print(f"  {key:<{width}}  {shown}")
