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

#: Each subcommand and the module that contributes it, in the order ``--help`` lists them. Only the
#: module of the subcommand being run is imported: ``symbio run`` checks its command line and config
#: files before it loads gtsam, pycolmap or a network, and no command pays for another's libraries.
SUBCOMMANDS = {
    "demo": "eval.demo",
    "synth": "frontends.synth.cli",
    "datasets": "frontends.datasets.cli",
    "posegraph": "slam_backend.cli",
    "vocab": "lcd.vocab_cli",
    "symbiolcd-train": "lcd.symbiolcd_train",
    "eval": "eval.eval_cli",
    "detectors": "eval.lcd_eval",
    "run": "eval.run_cli",
    "config": "eval.config_cli",
}
#: Options of ``symbio`` itself (before the subcommand).
TOP_LEVEL_OPTIONS = ("-v", "--verbose")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``symbio`` parser: every subcommand, or only ``command``'s (the one being run)."""
    import importlib

    parser = argparse.ArgumentParser(
        prog="symbio",
        description="Monocular SLAM with SymbioLCD2 loop closure and a GTSAM pose-graph backend.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    modules = [SUBCOMMANDS[command]] if command in SUBCOMMANDS else list(dict.fromkeys(SUBCOMMANDS.values()))
    for name in modules:
        importlib.import_module(name).add_parser(subparsers)
    return parser


def chosen_command(argv: Sequence[str]) -> str | None:
    """The subcommand ``argv`` runs (the first word after symbio's own options), if any."""
    for word in argv:
        if word not in TOP_LEVEL_OPTIONS:
            return word if word in SUBCOMMANDS else None
    return None


def main(argv: Sequence[str] | None = None) -> int:
    # File names that are not UTF-8 reach messages as lone surrogates: print them as escapes.
    for stream in (sys.stdout, sys.stderr):
        if hasattr(stream, "reconfigure"):
            stream.reconfigure(errors="backslashreplace")
    words = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(chosen_command(words))
    args = parser.parse_args(words)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s"
    )
    # evo logs every file it writes at INFO; our commands report their outputs themselves.
    logging.getLogger("evo").setLevel(logging.DEBUG if args.verbose else logging.WARNING)
    logging.getLogger("numexpr").setLevel(logging.WARNING)  # pandas' thread-count notice
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
