"""The components of a ``symbio run`` (frontend, loop detector, object detector, verifier, backend,
loop-closing settings) from a run YAML, ``--set`` overrides and the name options.

A run YAML has sections ``frontend``, ``detector``, ``object_detector``, ``verifier``, ``backend``,
``loop_closing``; each may name its component with ``name:``. A YAML without any section is the
frontend's own config. Every override remembers the file and line it came from, so errors about it
name them. Light on purpose: the CLI checks configs before it loads gtsam, pycolmap or a network.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from frontends.base import FRONTENDS
from frontends.config import Override, parse_override, read_yaml_mapping
from frontends.errors import ConfigError
from frontends.registry import Registry
from frontends.safe_yaml import short_repr
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS
from slam_backend.plugins import BACKENDS, VERIFIERS

SECTIONS = ("frontend", "detector", "object_detector", "verifier", "backend", "loop_closing")


@dataclass(frozen=True)
class Components:
    """Names and settings of every part of the pipeline (``--config`` sections, ``--set``)."""

    frontend: str = "mono-vo"
    detector: str = "symbiolcd2"
    #: Empty: the oracle on synthetic scenes (they carry GT objects), ssd-mobilenet elsewhere.
    object_detector: str = ""
    verifier: str = "pycolmap"
    backend: str = "gtsam"
    #: Per section: ``key=value`` overrides (from the YAML file first, then the command line).
    overrides: dict[str, list[str]] = field(default_factory=dict)

    def of(self, section: str) -> list[str]:
        return self.overrides.get(section, [])


def _flatten(mapping: dict[str, Any], where: Callable[[str], str], prefix: str = "") -> list[str]:
    """A YAML section as ``key=value`` overrides, each value dumped back to YAML; ``where`` gives
    the ``FILE:LINE`` of a dotted key, which errors about its override name."""
    items: list[str] = []
    for key, value in mapping.items():
        if isinstance(value, dict):
            items += _flatten(value, where, f"{prefix}{key}.")
        else:
            # A scalar document ends with "..."; the override wants the value alone.
            dumped = yaml.safe_dump(value, default_flow_style=True).removesuffix("\n").removesuffix("\n...")
            items.append(Override(f"{prefix}{key}={dumped}", where(f"{prefix}{key}")))
    return items


def load_components(
    config_path: Path | None, overrides: Sequence[str], names: dict[str, str | None]
) -> Components:
    """Components from a run YAML, ``--set`` overrides and the ``--frontend``/... name options."""
    chosen: dict[str, str] = {}
    per_section: dict[str, list[str]] = {section: [] for section in SECTIONS}
    if config_path is not None:
        mapping, lines = read_yaml_mapping(config_path)

        def where(dotted: str) -> str:
            return f"{config_path}:{lines.get(dotted, 1)}"

        if any(key in SECTIONS for key in mapping):
            registries: dict[str, Registry[Any]] = {
                "frontend": FRONTENDS,
                "detector": LOOP_DETECTORS,
                "object_detector": OBJECT_DETECTORS,
                "verifier": VERIFIERS,
                "backend": BACKENDS,
            }
            for key, value in mapping.items():
                if key not in SECTIONS:
                    raise ConfigError(
                        f"{where(str(key))}: unknown section {short_repr(key)} (expected one of {SECTIONS})"
                    )
                if not isinstance(value, dict):
                    raise ConfigError(f"{where(key)}: section {key!r} must be a mapping")
                value = dict(value)
                if "name" in value:
                    # Checked here: the registry's own error, later, could not name the line.
                    name, registry = value.pop("name"), registries.get(key)
                    installed = registry.names() if registry is not None else []
                    if name not in installed and not (key == "object_detector" and name == ""):  # "": default
                        raise ConfigError(
                            f"{where(f'{key}.name')}: unknown {key} {short_repr(name)}; "
                            f"installed: {', '.join(installed) or 'none'}"
                        )
                    chosen[key] = name

                def section_where(dotted: str, section: str = key) -> str:
                    return where(f"{section}.{dotted}")

                per_section[key] += _flatten(value, section_where)
        else:  # the frontend's own config file
            per_section["frontend"] += _flatten(mapping, where)
    for item in overrides:
        section, dot, rest = item.partition(".")
        # Errors about an override name it as the user typed it, section included.
        source = f"--set {short_repr(item)}"
        parse_override(Override(item, source))  # bad YAML is refused now, before the pipeline loads
        if dot and section in SECTIONS:
            per_section[section].append(Override(rest, source))
        else:
            per_section["frontend"].append(Override(item, source))
    for section, name in names.items():
        if name is not None:
            chosen[section] = name
    known = {f.name for f in fields(Components)}
    return Components(**{k: v for k, v in chosen.items() if k in known}, overrides=per_section)
