"""``symbio config [SECTION]``: every default of every component, as commented YAML.

One section per configurable component: ``frontend`` (mono-vo), ``replay``, each built-in loop
detector, the object detectors with settings, ``verifier``, ``backend``, ``loop_closing`` and
``orb`` (the place-recognition ORB preset). Each field has a one-line comment: the first sentence
of the ``#:`` comment above it in the source (``frontends.config_doc``). The YAML a section prints
is a valid config file of that component (``symbio run --config``'s sections, ``--set``).

``--markdown`` prints ``docs/config.md`` (``python -m eval.config_cli --markdown > docs/config.md``
regenerates it; a test keeps it current). A section's config class is imported only when that
section is printed, so ``symbio config frontend`` loads no gtsam, pycolmap or onnxruntime; the
``verifier``, ``backend``, ``loop_closing`` and ``onnx`` sections live in modules that do.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from frontends.config import apply_mapping
from frontends.config_doc import render_markdown_table, render_yaml
from frontends.errors import ConfigError

#: The command that regenerates ``docs/config.md``.
REGENERATE = "python -m eval.config_cli --markdown > docs/config.md"


@dataclass(frozen=True)
class Section:
    """One configurable component: its config class and how a run sets its values."""

    name: str
    #: ``module:ClassName`` of the config dataclass.
    config: str
    #: What the component is (one line).
    title: str
    #: How a run sets its values.
    usage: str
    #: ``module:NAME`` of a preset instance used instead of the class's defaults.
    preset: str = ""
    #: Values the component's factory fixes on top of the defaults (nested mapping).
    fixed: Mapping[str, Any] = field(default_factory=dict)

    def config_class(self) -> type:
        return _load(self.config)

    def defaults(self) -> Any:
        """The effective defaults: the preset or the class's defaults, with the fixed values."""
        config = _load(self.preset) if self.preset else self.config_class()()
        return apply_mapping(config, self.fixed, source=f"section {self.name}") if self.fixed else config


def _load(origin: str) -> Any:
    module, _, attribute = origin.partition(":")
    return getattr(importlib.import_module(module), attribute)


_DETECTOR = (
    "symbio run --detector {name} --set detector.KEY=VALUE; run YAML section `detector:` (name: {name})"
)
_OBJECTS = (
    "symbio run --object-detector {name} --set object_detector.KEY=VALUE; "
    "run YAML section `object_detector:` (name: {name})"
)


def _detector(name: str, config: str, title: str, fixed: Mapping[str, Any] | None = None) -> Section:
    usage = _DETECTOR.format(name=name)
    if fixed:
        usage += "; " + ", ".join(f"{k}.{kk}={vv}" for k, v in fixed.items() for kk, vv in v.items())
        usage += " is fixed by the name"
    return Section(name, config, title, usage, fixed=fixed or {})


#: Every section, in the order ``symbio config`` prints them.
SECTIONS: tuple[Section, ...] = (
    Section(
        "frontend",
        "frontends.mono_vo.config:MonoVoConfig",
        "mono-vo, the monocular visual-odometry frontend (the default)",
        "symbio run --set KEY=VALUE (or frontend.KEY=VALUE); run YAML section `frontend:`, "
        "or a YAML without sections",
    ),
    Section(
        "replay",
        "frontends.replay:ReplayConfig",
        "replay, the frontend that takes its poses from a trajectory file",
        "symbio run --frontend replay --set KEY=VALUE; run YAML section `frontend:` (name: replay)",
    ),
    _detector("symbiolcd2", "lcd.symbiolcd2:SymbioLCD2Config", "SymbioLCD2 loop detector (the default)"),
    _detector(
        "symbiolcd2-two-tier",
        "lcd.symbiolcd2:SymbioLCD2Config",
        "SymbioLCD2 with objects and the features in their boxes only (ablation)",
        {"graph": {"tiers": 2}},
    ),
    _detector(
        "symbiolcd2-flat",
        "lcd.symbiolcd2:SymbioLCD2Config",
        "SymbioLCD2 with features only (flat ablation)",
        {"graph": {"tiers": 1}},
    ),
    _detector(
        "symbiolcd",
        "lcd.symbiolcd:SymbioLCDConfig",
        "SymbioLCD (Kim et al., IROS 2021), the paper's baseline loop detector",
    ),
    _detector(
        "vbow",
        "lcd.vbow:VbowConfig",
        "DBoW2 bag-of-words loop detector, as ORB-SLAM's loop detection uses it",
    ),
    Section(
        "ssd-mobilenet",
        "lcd.objects.ssd_cv2:SsdConfig",
        "SSD-MobileNet-v2 COCO object detector on OpenCV DNN",
        _OBJECTS.format(name="ssd-mobilenet"),
    ),
    Section("onnx", "lcd.objects.onnx:OnnxConfig", "an ONNX object detector", _OBJECTS.format(name="onnx")),
    Section(
        "oracle",
        "lcd.objects.oracle:OracleConfig",
        "ground-truth objects of synthetic scenes, optionally degraded",
        _OBJECTS.format(name="oracle"),
    ),
    Section(
        "verifier",
        "slam_backend.verify:VerifierConfig",
        "pycolmap geometric verification of loop candidates",
        "symbio run --set verifier.KEY=VALUE; run YAML section `verifier:`",
    ),
    Section(
        "backend",
        "slam_backend.posegraph:BackendConfig",
        "gtsam pose-graph backend",
        "symbio run --set backend.KEY=VALUE; run YAML section `backend:`",
    ),
    Section(
        "loop_closing",
        "slam_backend.pipeline:LoopClosingConfig",
        "loop closing: proposals, verification, segment links, global BA",
        "symbio run --set loop_closing.KEY=VALUE; run YAML section `loop_closing:`",
    ),
    Section(
        "orb",
        "frontends.orb:OrbConfig",
        "ORB extraction, place-recognition preset (mono-vo tracks with its own: frontend `orb:`)",
        "symbio vocab build --set KEY=VALUE; the replay frontend's `orb:`",
    ),
)
#: Other names of sections (component names and ``symbio run``'s section names).
ALIASES = {"mono-vo": "frontend", "detector": "symbiolcd2", "pycolmap": "verifier", "gtsam": "backend"}


def find_section(name: str) -> Section:
    name = ALIASES.get(name, name)
    for section in SECTIONS:
        if section.name == name:
            return section
    raise ConfigError(f"unknown config section {name!r}; known: {', '.join(s.name for s in SECTIONS)}")


def section_header(section: Section) -> str:
    return (
        f"# == {section.name}: {section.title}\n"
        f"# {section.config.replace(':', '.')}; set with: {section.usage}"
    )


def render_section(section: Section) -> str:
    """A section as commented YAML under a header comment."""
    return f"{section_header(section)}\n{render_yaml(section.defaults())}\n"


def render_markdown(sections: Sequence[Section] = SECTIONS) -> str:
    """``docs/config.md``: every section's defaults as a table."""
    out = [
        "# Configuration reference",
        "",
        f"Generated from the config dataclasses by `{REGENERATE}` (or `symbio config --markdown`);",
        "do not edit: change the `#:` comments above the fields and regenerate. A test keeps it current.",
        "",
        "`symbio config [SECTION]` prints the same defaults as commented YAML that loads back as a",
        "config file. Each meaning is the field's one-line comment in the source; the measurements",
        "behind the defaults are in the experiment log (docs/2026-12-06-config-evidence.md and the",
        "other dated notes in docs/).",
        "",
        "Sections: " + ", ".join(f"[`{s.name}`](#{s.name})" for s in sections) + ".",
    ]
    for section in sections:
        out += [
            "",
            f"## {section.name}",
            "",
            f"{section.title[0].upper()}{section.title[1:]}: `{section.config.replace(':', '.')}`.",
            f"Set with: {section.usage}.",
            "",
            render_markdown_table(section.defaults()),
        ]
    return "\n".join(out) + "\n"


def add_parser(subparsers: Any) -> None:
    parser = subparsers.add_parser(
        "config",
        help="print every default setting with its meaning (commented YAML)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "section",
        nargs="?",
        metavar="SECTION",
        help="one component (" + ", ".join(s.name for s in SECTIONS) + "); default: all",
    )
    parser.add_argument("--list", action="store_true", help="list the sections")
    parser.add_argument("--markdown", action="store_true", help="print docs/config.md (every section)")
    parser.set_defaults(handler=run_config)


def run_config(args: argparse.Namespace) -> int:
    if args.list:
        for section in SECTIONS:
            print(f"{section.name:<20} {section.title}")
        return 0
    if args.markdown:
        print(render_markdown(), end="")
        return 0
    sections = [find_section(args.section)] if args.section else list(SECTIONS)
    print("\n".join(render_section(section) for section in sections), end="")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    from eval.cli import main as symbio

    return symbio(["config", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
