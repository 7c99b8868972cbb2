"""Frozen-dataclass configs, overridable from a YAML file and from ``key=value`` CLI strings.

Every swappable component has a frozen config dataclass with defaults. ``load_config`` applies a
YAML mapping and then ``--set key=value`` overrides (dotted keys reach nested configs), checks each
value against the field's type and names the file and line of anything it rejects.
"""

from __future__ import annotations

import dataclasses
import re
import types
import typing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import yaml

from frontends.errors import ConfigError

T = TypeVar("T")


def load_config(cls: type[T], yaml_path: str | Path | None = None, overrides: Sequence[str] = ()) -> T:
    """Build ``cls`` from its defaults, then a YAML file, then ``key=value`` overrides."""
    config = cls()
    if yaml_path is not None:
        mapping, lines = read_yaml_mapping(yaml_path)
        config = apply_mapping(config, mapping, source=str(yaml_path), lines=lines)
    for item in overrides:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"override {item!r}: expected key=value")
        try:
            value = yaml.safe_load(raw) if raw.strip() else ""
        except yaml.YAMLError as exc:
            raise ConfigError(f"override {item!r}: value is not valid YAML ({exc})") from None
        nested: dict[str, Any] = {}
        cursor = nested
        parts = key.strip().split(".")
        for part in parts[:-1]:
            cursor = cursor.setdefault(part, {})
        cursor[parts[-1]] = value
        config = apply_mapping(config, nested, source=f"override {item!r}")
    return config


def read_yaml_mapping(path: str | Path) -> tuple[dict[str, Any], dict[str, int]]:
    """Read a YAML mapping and the 1-based line of every (dotted) key, for error messages."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read config file ({exc})") from None
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else str(path)
        raise ConfigError(f"{where}: invalid YAML ({getattr(exc, 'problem', exc)})") from None
    if data is None:
        return {}, {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}:1: expected a mapping of config keys, got {type(data).__name__}")
    lines: dict[str, int] = {}
    _collect_key_lines(node, "", lines)
    return data, lines


def _collect_key_lines(node: yaml.Node | None, prefix: str, lines: dict[str, int]) -> None:
    if not isinstance(node, yaml.MappingNode):
        return
    for key_node, value_node in node.value:
        key = f"{prefix}{key_node.value}"
        lines[key] = key_node.start_mark.line + 1
        _collect_key_lines(value_node, key + ".", lines)


def apply_mapping(
    config: T,
    mapping: Mapping[str, Any],
    source: str,
    lines: Mapping[str, int] | None = None,
    prefix: str = "",
) -> T:
    """Return ``config`` with the fields in ``mapping`` replaced, each checked against its type."""
    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        raise TypeError("apply_mapping needs a dataclass instance")
    hints = typing.get_type_hints(type(config))
    fields = {f.name for f in dataclasses.fields(config)}
    changes: dict[str, Any] = {}
    for key, value in mapping.items():
        dotted = f"{prefix}{key}"
        where = f"{source}:{lines[dotted]}" if lines and dotted in lines else source
        if key not in fields:
            known = ", ".join(sorted(fields))
            raise ConfigError(f"{where}: unknown key {dotted!r} for {type(config).__name__} (known: {known})")
        current = getattr(config, key)
        if dataclasses.is_dataclass(current) and not isinstance(current, type):
            if not isinstance(value, Mapping):
                raise ConfigError(f"{where}: {dotted!r} must be a mapping")
            changes[key] = apply_mapping(current, value, source, lines, prefix=dotted + ".")
        else:
            changes[key] = coerce(value, hints[key], f"{where}: {dotted!r}")
    return dataclasses.replace(config, **changes)


_EXPONENT = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+")


def coerce(value: Any, annotation: Any, what: str) -> Any:
    """Check ``value`` against a field annotation; convert lossless cases (int -> float, list -> tuple)."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for option in (a for a in args if a is not type(None)):
            try:
                return coerce(value, option, what)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{what}: invalid value {value!r}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{what}: must be one of {list(args)}, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{what}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(coerce(v, args[0], what) for v in value)
        if len(value) != len(args):
            raise ConfigError(f"{what}: expected {len(args)} values, got {len(value)}")
        return tuple(coerce(v, a, what) for v, a in zip(value, args, strict=True))
    if annotation is float:
        if isinstance(value, str):
            # YAML 1.1 reads exponents without a dot ("1e-6") as strings.
            value = float(value) if _EXPONENT.fullmatch(value.strip()) else value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{what}: expected a number, got {value!r}")
        return float(value)
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{what}: expected an integer, got {value!r}")
        return value
    if annotation is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{what}: expected true or false, got {value!r}")
        return value
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"{what}: expected a string, got {value!r}")
        return value
    return value


def config_to_dict(config: Any) -> dict[str, Any]:
    """A plain dict of a (nested) config dataclass, tuples as lists: ready for YAML/JSON."""

    def plain(value: Any) -> Any:
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        return value

    return plain(dataclasses.asdict(config))
