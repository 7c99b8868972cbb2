"""Name -> implementation registries for the swappable parts (datasets, detectors, backends, ...).

Built-in implementations are listed as ``"module:attribute"`` strings and imported on first use, so
that listing names never imports heavy dependencies. Other packages add implementations through the
entry-point group given to the registry (e.g. ``symbio.loop_detectors``).
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from importlib.metadata import entry_points
from typing import Any, Generic, TypeVar

from frontends.errors import ConfigError

T = TypeVar("T")


class Registry(Generic[T]):
    def __init__(self, kind: str, group: str, builtins: Mapping[str, str]) -> None:
        self.kind = kind
        self.group = group
        self._builtins = dict(builtins)

    def _entry_points(self) -> dict[str, Any]:
        return {ep.name: ep for ep in entry_points(group=self.group)}

    def names(self) -> list[str]:
        return sorted(set(self._builtins) | set(self._entry_points()))

    def origin(self, name: str) -> str:
        """Where ``name`` comes from: ``module:attribute`` of a built-in or an entry point."""
        if name in self._builtins:
            return self._builtins[name]
        return str(self._entry_points()[name].value)

    def load(self, name: str) -> T:
        if name not in self._builtins and name not in self._entry_points():
            raise ConfigError(f"unknown {self.kind} {name!r}; installed: {', '.join(self.names())}")
        origin = self.origin(name)
        module, _, attribute = origin.partition(":")
        try:  # a broken plugin package must not surface as a bare ImportError
            return getattr(importlib.import_module(module), attribute)
        except (ImportError, AttributeError) as exc:
            raise ConfigError(f"{self.kind} {name!r} ({origin}) could not be loaded: {exc}") from exc
