"""``symbio eval``: ``lcd`` (``eval.lcd_eval``), ``table`` and ``sweep`` (``eval.paper.table``)."""

from __future__ import annotations

from typing import Any

from eval.lcd_eval import add_lcd_parser
from eval.paper.table import add_table_parsers


def add_parser(subparsers: Any) -> None:
    evaluate = subparsers.add_parser("eval", help="evaluate loop detectors and SLAM runs")
    commands = evaluate.add_subparsers(dest="eval_command", metavar="SUBCOMMAND", required=True)
    add_lcd_parser(commands)
    add_table_parsers(commands)
