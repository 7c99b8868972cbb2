"""The ``symbio`` command line: one entry point, one subcommand per job.

Each package contributes subcommands through an ``add_parser(subparsers)`` function; they are
imported here so ``symbio --help`` lists everything installed.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence

from frontends.errors import SymbioError

#: Modules that contribute subcommands, in the order ``--help`` lists them.
SUBCOMMAND_MODULES = (
    "eval.demo",
    "frontends.synth.cli",
    "frontends.datasets.cli",
    "slam_backend.cli",
    "lcd.vocab_cli",
    "lcd.symbiolcd_train",
    "eval.lcd_eval",
    "eval.run",
)


def build_parser() -> argparse.ArgumentParser:
    import importlib

    parser = argparse.ArgumentParser(
        prog="symbio",
        description="Monocular SLAM with SymbioLCD2 loop closure and a GTSAM pose-graph backend.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in SUBCOMMAND_MODULES:
        importlib.import_module(name).add_parser(subparsers)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s"
    )
    # evo logs every file it writes at INFO; our commands report their outputs themselves.
    logging.getLogger("evo").setLevel(logging.DEBUG if args.verbose else logging.WARNING)
    # Dask logs every worker and connection at INFO; sweeps report their jobs themselves. Dask reads
    # its logging config from the environment when imported (here and in worker processes).
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "debug" if args.verbose else "warning")
    try:
        return int(args.handler(args) or 0)
    except SymbioError as exc:
        print(f"symbio: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # commands write what they processed before re-raising
        print("symbio: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
