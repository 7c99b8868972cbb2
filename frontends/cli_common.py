"""Helpers shared by the ``symbio`` subcommands of every package."""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from frontends.errors import OutputError
from frontends.safe_io import atomic_write_text, describe_os_error


def add_json_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--json", metavar="PATH", type=Path, help="write the measured figures as a flat JSON object"
    )


def add_set_option(parser: argparse.ArgumentParser, help: str) -> None:
    """``--set KEY=VALUE`` (repeatable) into ``args.overrides``."""
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help=help
    )


def flat_json(figures: Mapping[str, Any]) -> str:
    """A flat JSON object of scalar figures (NaN/inf become null, numpy scalars plain numbers)."""
    flat: dict[str, Any] = {}
    for key, value in figures.items():
        if hasattr(value, "item") and callable(value.item):
            value = value.item()
        if isinstance(value, float) and not math.isfinite(value):
            value = None
        if isinstance(value, (Mapping, list, tuple)):
            raise TypeError(f"--json output must be flat; {key!r} is a {type(value).__name__}")
        flat[key] = value
    return json.dumps(flat, indent=2, sort_keys=True) + "\n"


def write_json(path: str | Path | None, figures: Mapping[str, Any]) -> None:
    """Write ``flat_json(figures)`` to ``path`` (atomically; nothing when ``path`` is None)."""
    if path is None:
        return
    text = flat_json(figures)
    target = Path(path)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(target.parent, f"cannot create the folder ({describe_os_error(exc)})") from None
    atomic_write_text(target, text)


def print_figures(figures: Mapping[str, Any]) -> None:
    """Print figures as an aligned two-column table."""
    width = max((len(k) for k in figures), default=0)
    for key, value in figures.items():
        shown = f"{value:.4g}" if isinstance(value, float) else str(value)
        print(f"  {key:<{width}}  {shown}")
