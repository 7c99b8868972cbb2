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

from frontends import safe_yaml
from frontends.errors import ConfigError
from frontends.safe_yaml import short_repr

T = TypeVar("T")


def load_config(cls: type[T], yaml_path: str | Path | None = None, overrides: Sequence[str] = ()) -> T:
    """Build ``cls`` from its defaults, then a YAML file, then ``key=value`` overrides."""
    config = cls()
    if yaml_path is not None:
        mapping, lines = read_yaml_mapping(yaml_path)
        config = apply_mapping(config, mapping, source=str(yaml_path), lines=lines)
    for item in overrides:
        nested, source = parse_override(item)
        config = apply_mapping(config, nested, source=source)
    return config


class Override(str):
    """A ``key=value`` override standing for an entry of a YAML file: its errors name that file and line."""

    where: str

    def __new__(cls, text: str, where: str) -> Override:
        item = super().__new__(cls, text)
        item.where = where
        return item

    def __reduce__(self) -> tuple[type[Override], tuple[str, str]]:
        # str's own pickling would call __new__ without ``where``.
        return type(self), (str(self), self.where)


_SURROGATE = re.compile("[\udc80-\udcff]")


def parse_override(item: str) -> tuple[dict[str, Any], str]:
    """``key=value`` (dotted keys reach nested configs; the value is YAML) as a nested mapping, and
    the source to name in errors about it."""
    source = item.where if isinstance(item, Override) else f"override {short_repr(item)}"
    key, sep, raw = item.partition("=")
    if not sep or not key.strip():
        raise ConfigError(f"{source}: expected key=value")
    try:
        if _SURROGATE.search(raw):
            # A file name that is not UTF-8 (a shell argument's bytes kept as lone surrogates): YAML
            # cannot carry it, and a path is what such a value is, so it is taken as a string.
            value: Any = raw
        else:
            value = safe_yaml.load(raw, with_lines=False)[0] if raw.strip() else ""
    except safe_yaml.YamlInputError as exc:
        raise ConfigError(f"{source}: {exc.reason}") from None
    nested: dict[str, Any] = {}
    cursor = nested
    parts = key.strip().split(".")
    for part in parts[:-1]:
        cursor = cursor.setdefault(part, {})
    cursor[parts[-1]] = value
    return nested, source


def read_yaml_mapping(path: str | Path) -> tuple[dict[str, Any], dict[str, int]]:
    """Read a YAML mapping (bounded: ``frontends.safe_yaml``) and the 1-based line of every dotted
    key (``a.b``; list items as ``a.0``), for error messages."""
    path = Path(path)
    try:
        data, lines = safe_yaml.load(safe_yaml.read_text(path))
    except safe_yaml.YamlInputError as exc:
        where = f"{path}:{exc.line}" if exc.line is not None else str(path)
        raise ConfigError(f"{where}: {exc.reason}") from None
    if data is None:
        return {}, {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}:1: expected a mapping of config keys, got {type(data).__name__}")
    return data, lines


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
            raise ConfigError(
                f"{where}: unknown key {short_repr(dotted)} for {type(config).__name__} (known: {known})"
            )
        current = getattr(config, key)
        if dataclasses.is_dataclass(current) and not isinstance(current, type):
            if not isinstance(value, Mapping):
                raise ConfigError(f"{where}: {short_repr(dotted)} must be a mapping")
            changes[key] = apply_mapping(current, value, source, lines, prefix=dotted + ".")
        else:
            changes[key] = coerce(value, hints[key], f"{where}: {short_repr(dotted)}")
    try:
        return dataclasses.replace(config, **changes)
    except ConfigError as exc:  # a __post_init__ check (e.g. "repeats must be >= 1") knows no file
        message = str(exc)
        raise ConfigError(message if message.startswith(source) else f"{source}: {message}") from None


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
        raise ConfigError(errors[0] if errors else f"{what}: invalid value {short_repr(value)}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{what}: must be one of {list(args)}, got {short_repr(value)}")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{what}: expected a list, got {short_repr(value)}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(coerce(v, args[0], what) for v in value)
        if len(value) != len(args):
            raise ConfigError(f"{what}: expected {len(args)} values, got {len(value)}")
        return tuple(coerce(v, a, what) for v, a in zip(value, args, strict=True))
    if annotation is float:
        number = safe_yaml.number(value)  # also "1e-6", which YAML 1.1 reads as a string
        if number is None:
            raise ConfigError(f"{what}: expected a number, got {short_repr(value)}")
        return number
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{what}: expected an integer, got {short_repr(value)}")
        return value
    if annotation is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{what}: expected true or false, got {short_repr(value)}")
        return value
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"{what}: expected a string, got {short_repr(value)}")
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
