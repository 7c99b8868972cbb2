"""Config dataclasses rendered for people: commented YAML and Markdown tables of every default.

Each config field is documented by the ``#:`` comment above it in the source (Sphinx's convention;
comments are not docstrings, so they are read from the source with ``ast``). Rendered, a comment
becomes one line, its first sentence, so the output has one comment line per field. A comment
belongs to the one field below it (a field right below another without a comment of its own has
none: ``undocumented_fields`` lists them); a nested config without a ``#:`` comment is described by
its class docstring. The YAML loads back with ``frontends.config.load_config`` into an equal config.

Pure functions of the classes and instances given: the CLI (``symbio config``) gathers them.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import math
import re
import textwrap
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import yaml

#: Words that end with a period without ending a sentence.
_ABBREVIATIONS = ("e.g", "i.e", "vs", "cf", "etc", "approx", "resp", "incl", "eq", "fig", "no")


@dataclass(frozen=True)
class FieldDoc:
    """The ``#:`` comment of one dataclass field and where it is."""

    name: str
    #: The comment's text, its lines joined by spaces ("" when the field has none).
    comment: str
    #: Source file and 1-based line of the field's annotation.
    file: str
    line: int
    #: How many ``#:`` lines the comment has (0: none).
    comment_lines: int


def first_sentence(text: str) -> str:
    """``text`` up to its first sentence end (". " outside parentheses, not after "e.g." and the
    like), reST double backticks as single ones: one line of a rendered comment."""
    text = " ".join(text.split()).replace("``", "`")
    depth = 0
    for i, char in enumerate(text):
        if char in "([":
            depth += 1
        elif char in ")]":
            depth = max(depth - 1, 0)
        elif char == "." and depth == 0 and text[i + 1 : i + 2] == " " and text[i - 1 : i] != ".":
            word = re.split(r"[\s(]", text[:i])[-1].lower()
            if word not in _ABBREVIATIONS:
                return text[: i + 1]
    return text


@functools.cache
def field_docs(cls: type) -> dict[str, FieldDoc]:
    """The ``#:`` comment of every field of dataclass ``cls`` (its own and its bases'), by name."""
    docs: dict[str, FieldDoc] = {}
    for klass in reversed(cls.__mro__):
        if dataclasses.is_dataclass(klass) and "__dataclass_fields__" in vars(klass):
            docs.update(_own_field_docs(klass))
    return {f.name: docs.get(f.name, FieldDoc(f.name, "", "?", 0, 0)) for f in dataclasses.fields(cls)}


def _own_field_docs(cls: type) -> dict[str, FieldDoc]:
    try:
        lines, start = inspect.getsourcelines(cls)
        file = inspect.getsourcefile(cls) or "?"
    except (OSError, TypeError):  # no source (a compiled or interactive class): no comments
        return {}
    tree = ast.parse(textwrap.dedent("".join(lines)))
    node = tree.body[0]
    if not isinstance(node, ast.ClassDef):
        return {}
    docs: dict[str, FieldDoc] = {}
    for statement in node.body:
        if not (isinstance(statement, ast.AnnAssign) and isinstance(statement.target, ast.Name)):
            continue
        name = statement.target.id
        comment: list[str] = []
        row = statement.lineno - 2  # 0-based index of the line above the field
        while row >= 0 and lines[row].strip().startswith("#:"):
            comment.insert(0, lines[row].strip().removeprefix("#:").strip())
            row -= 1
        docs[name] = FieldDoc(name, " ".join(comment), file, start + statement.lineno - 1, len(comment))
    return docs


def field_comment(cls: type, name: str, value: Any = None) -> str:
    """The one-line comment of field ``name`` of ``cls`` (``value``: its value, for a nested
    config's class docstring); "" when it has none."""
    text = field_docs(cls)[name].comment
    if not text and dataclasses.is_dataclass(value):
        text = inspect.getdoc(type(value)) or ""
        if text == inspect.getdoc(object) or text.startswith(type(value).__name__ + "("):
            text = ""  # the dataclass's generated signature, not a description
    return first_sentence(text)


def iter_fields(config: Any, prefix: str = "") -> Iterator[tuple[str, Any, str]]:
    """Every leaf field of a (nested) config instance: dotted key, value and one-line comment."""
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            yield from iter_fields(value, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", value, field_comment(type(config), f.name, value)


def undocumented_fields(config: Any, prefix: str = "") -> list[str]:
    """Dotted keys of the fields of ``config`` (nested configs included) without a ``#:`` comment
    (a nested config's class docstring counts as its comment)."""
    missing = []
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if not field_comment(type(config), f.name, value):
            missing.append(f"{prefix}{f.name}")
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            missing += undocumented_fields(value, f"{prefix}{f.name}.")
    return missing


def yaml_value(value: Any) -> str:
    """``value`` as a one-line YAML flow value that ``frontends.safe_yaml`` reads back equal."""
    if isinstance(value, float) and not math.isfinite(value):
        return ".nan" if math.isnan(value) else (".inf" if value > 0 else "-.inf")
    plain = _plain(value)
    dumped = yaml.safe_dump(plain, default_flow_style=True, width=math.inf, allow_unicode=True)
    return dumped.removesuffix("\n").removesuffix("\n...")


def _plain(value: Any) -> Any:
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (bool, int, float, str)) or value is None:
        return value
    return str(value)  # a Path or an enum: as the string a YAML file would give


def render_yaml(config: Any, indent: int = 0) -> str:
    """``config`` (a dataclass instance; nested configs as nested mappings) as YAML with a
    ``# comment`` line above every field that has one."""
    pad = "  " * indent
    out: list[str] = []
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        comment = field_comment(type(config), f.name, value)
        if comment:
            out.append(f"{pad}# {comment}")
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            body = render_yaml(value, indent + 1)
            out.append(f"{pad}{f.name}:" + ("\n" + body if body else " {}"))
        else:
            out.append(f"{pad}{f.name}: {yaml_value(value)}")
    return "\n".join(out)


def render_markdown_table(config: Any) -> str:
    """``config``'s leaf fields as a Markdown table: dotted key, default, meaning."""
    rows = ["| key | default | meaning |", "| --- | --- | --- |"]
    for key, value, comment in iter_fields(config):
        default, meaning = yaml_value(value).replace("|", "\\|"), comment.replace("|", "\\|")
        rows.append(f"| `{key}` | `{default}` | {meaning} |")
    if len(rows) == 2:
        return "No settings."
    return "\n".join(rows)
