"""The one way this project reads YAML (configs, ``--set`` values, calibration files): bounded.

PyYAML's ``safe_load`` expands aliases without limit (a "billion laughs" file of a few hundred bytes
builds gigabytes), recurses once per nesting level (a RecursionError on deep nesting) and lets a
repeated key silently replace the first. ``load`` composes the node graph with a loader that counts,
as it goes, the aliases, the nodes after alias expansion and the nesting depth (aliases included),
refuses duplicate keys, and only then constructs Python objects. Every refusal is a
``YamlInputError`` carrying the 1-based line; callers turn it into their documented error type.
"""

from __future__ import annotations

import re
import reprlib
from pathlib import Path
from typing import Any

import yaml

#: Config and calibration files are a few kilobytes; anything larger is refused unread.
MAX_BYTES = 1 << 20
#: Nesting levels, counted through aliases (the constructor and our walks recurse once per level).
MAX_DEPTH = 100
MAX_ALIASES = 100
#: Nodes after alias expansion: what the constructed objects and every walk over them cost.
MAX_NODES = 100_000

_MERGE_TAG = "tag:yaml.org,2002:merge"


class YamlInputError(Exception):
    """Why a YAML text was refused, with its 1-based line (None: the text as a whole)."""

    def __init__(self, reason: str, line: int | None = None) -> None:
        self.reason = reason
        self.line = line
        super().__init__(f"line {line}: {reason}" if line is not None else reason)


_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxlist, _REPR.maxtuple, _REPR.maxdict = 3, 8, 8, 6
_REPR.maxstring, _REPR.maxother = 70, 70


def short_repr(value: Any, limit: int = 80) -> str:
    """``repr(value)`` cut to ``limit`` characters, never built in full (values may be huge)."""
    text = _REPR.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _clip(text: str, limit: int = 120) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


_EXPONENT = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")


def number(value: Any) -> float | None:
    """``value`` as a float if it is a YAML number, else None.

    YAML 1.1 reads exponents without a dot ("1e-6", "5.25e2" is fine) as strings; they are numbers
    to anyone writing a config or a calibration, so they count as such here.
    """
    if isinstance(value, str) and _EXPONENT.fullmatch(value.strip()):
        return float(value)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        return float(value)
    except OverflowError:  # an integer beyond float range
        return None


def read_text(path: Path, max_bytes: int = MAX_BYTES) -> str:
    """The UTF-8 text of ``path``, refused (not read) past ``max_bytes``."""
    try:
        with path.open("rb") as handle:
            data = handle.read(max_bytes + 1)
    except FileNotFoundError:
        raise YamlInputError("file not found") from None
    except OSError as exc:
        raise YamlInputError(f"cannot read file ({exc.strerror or exc})") from None
    if len(data) > max_bytes:
        raise YamlInputError(f"larger than {max_bytes} bytes: not a config or calibration file")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise YamlInputError(f"not UTF-8 text (byte 0x{data[exc.start]:02x})", line) from None


class _BoundedLoader(yaml.SafeLoader):
    """SafeLoader whose composer refuses what would be too large, too deep or ambiguous."""

    def __init__(self, text: str) -> None:
        super().__init__(text)
        self._depth = 0
        self._aliases = 0
        self._nodes = 0
        # id(node) -> (nodes after expansion, height) of every finished node: what an alias adds.
        self._shapes: dict[int, tuple[int, int]] = {}

    def _grow(self, nodes: int, line: int) -> None:
        self._nodes += nodes
        if self._nodes > MAX_NODES:
            raise YamlInputError(f"more than {MAX_NODES} values once aliases are expanded", line)

    def fetch_flow_collection_start(self, TokenClass: type[yaml.Token]) -> None:
        # Refused in the scanner already: it looks ahead over every open "[" of the last 1024
        # characters for each token, which costs seconds on "[[[[..." before the composer sees it.
        if self.flow_level >= MAX_DEPTH:
            raise YamlInputError(f"nested deeper than {MAX_DEPTH} levels", self.line + 1)
        super().fetch_flow_collection_start(TokenClass)

    def compose_node(self, parent: yaml.Node | None, index: int) -> yaml.Node | None:
        event = self.peek_event()
        line = event.start_mark.line + 1
        if isinstance(event, yaml.AliasEvent):
            self._aliases += 1
            if self._aliases > MAX_ALIASES:
                raise YamlInputError(f"more than {MAX_ALIASES} aliases", line)
            target = self.anchors.get(event.anchor)
            if target is not None:  # an undefined alias is PyYAML's ComposerError
                shape = self._shapes.get(id(target))
                if shape is None:  # the anchored node is still open: an infinite structure
                    raise YamlInputError(f"alias *{_clip(str(event.anchor))} refers to itself", line)
                self._grow(shape[0], line)
                if self._depth + shape[1] > MAX_DEPTH:
                    raise YamlInputError(f"nested deeper than {MAX_DEPTH} levels (through an alias)", line)
            return super().compose_node(parent, index)
        self._depth += 1
        if self._depth > MAX_DEPTH:
            raise YamlInputError(f"nested deeper than {MAX_DEPTH} levels", line)
        self._grow(1, line)
        try:
            node = super().compose_node(parent, index)
        finally:
            self._depth -= 1
        assert node is not None  # only an alias or a document end composes to None
        children: list[yaml.Node] = []
        if isinstance(node, yaml.SequenceNode):
            children = node.value
        elif isinstance(node, yaml.MappingNode):
            _refuse_duplicate_keys(node)
            children = [part for pair in node.value for part in pair]
        shapes = [self._shapes[id(child)] for child in children]
        self._shapes[id(node)] = (1 + sum(s[0] for s in shapes), 1 + max((s[1] for s in shapes), default=0))
        return node

    def construct_object(self, node: yaml.Node, deep: bool = False) -> Any:
        try:
            return super().construct_object(node, deep)
        except (ValueError, OverflowError) as exc:  # e.g. an int of 5000 digits, a 13th month
            raise YamlInputError(f"invalid value ({_clip(str(exc))})", _line(node)) from None


def _line(node: yaml.Node) -> int:
    return int(node.start_mark.line) + 1


def _refuse_duplicate_keys(node: yaml.MappingNode) -> None:
    seen: dict[tuple[str, str], int] = {}
    for key_node, _ in node.value:
        if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == _MERGE_TAG:
            continue  # merged keys ("<<: *base") may be overridden: that is what merging means
        key = (key_node.tag, key_node.value)
        if key in seen:
            raise YamlInputError(
                f"duplicate key {short_repr(key_node.value)} (lines {seen[key]} and {_line(key_node)})",
                _line(key_node),
            )
        seen[key] = _line(key_node)


def load(text: str, with_lines: bool = True) -> tuple[Any, dict[str, int]]:
    """The data of one YAML document and the 1-based line of every dotted key (``a.b``, ``list.0``).

    Raises ``YamlInputError`` (with the line) for invalid YAML and for anything past the limits.
    """
    if len(text) > MAX_BYTES:
        raise YamlInputError(f"longer than {MAX_BYTES} characters")
    try:
        loader = _BoundedLoader(text)  # the reader checks every character here
    except yaml.reader.ReaderError as exc:
        line = text.count("\n", 0, exc.position) + 1
        raise YamlInputError(f"invalid YAML (character #x{exc.character:04x} is not allowed)", line) from None
    try:
        node = loader.get_single_node()
        data = loader.construct_document(node) if node is not None else None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        problem = exc.problem or exc.context or "invalid YAML"
        raise YamlInputError(f"invalid YAML ({_clip(problem)})", mark.line + 1 if mark else None) from None
    except yaml.YAMLError as exc:
        raise YamlInputError(f"invalid YAML ({_clip(str(exc))})") from None
    finally:
        loader.dispose()
    lines: dict[str, int] = {}
    if with_lines and node is not None:
        _collect_lines(node, "", lines)
    return data, lines


def _collect_lines(node: yaml.Node, prefix: str, lines: dict[str, int]) -> None:
    # Bounded by the loader: at most MAX_NODES visits (aliases included), MAX_DEPTH deep.
    if isinstance(node, yaml.MappingNode):
        for key_node, value_node in node.value:  # merged pairs first, explicit keys win
            if isinstance(key_node, yaml.ScalarNode):
                key = f"{prefix}{key_node.value}"
                lines[key] = _line(key_node)
                _collect_lines(value_node, key + ".", lines)
    elif isinstance(node, yaml.SequenceNode):
        for index, item in enumerate(node.value):
            key = f"{prefix}{index}"
            lines[key] = _line(item)
            _collect_lines(item, key + ".", lines)
