"""``symbio config``: every default printed as commented YAML that loads back, and docs/config.md."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from eval.cli import main as symbio
from eval.config_cli import REGENERATE, SECTIONS, find_section, render_markdown, render_section
from frontends.config import load_config
from frontends.config_doc import field_docs, first_sentence, render_yaml, undocumented_fields
from frontends.errors import ConfigError
from lcd.base import LOOP_DETECTORS, OBJECT_DETECTORS

REPO_ROOT = Path(__file__).resolve().parent.parent
CONFIG_MD = REPO_ROOT / "docs" / "config.md"

#: Fields without a ``#:`` comment yet (none left: every config field has one).
KNOWN_UNDOCUMENTED: set[str] = set()


@dataclasses.dataclass(frozen=True)
class Inner:
    """A nested config. More text that is not rendered."""

    #: Radius (m). The rest of the explanation
    #: spans lines.
    radius: float = 1.0


@dataclasses.dataclass(frozen=True)
class Outer:
    #: How many (e.g. three). Not rendered.
    count: int = 3
    label: str | None = None
    #: Sizes (px; ORB-SLAM: 1, 2).
    sizes: tuple[int, ...] = (1, 2)
    inner: Inner = dataclasses.field(default_factory=Inner)


def test_first_sentence() -> None:
    assert first_sentence("One (a. b) two, e.g. three. Four.") == "One (a. b) two, e.g. three."
    assert first_sentence("... or this many. More.") == "... or this many."
    assert first_sentence("No end") == "No end"
    assert first_sentence("Uses ``x``\n  here. Then") == "Uses `x` here."


def test_render_yaml_comments_and_nesting(tmp_path: Path) -> None:
    text = render_yaml(Outer())
    assert text.splitlines() == [
        "# How many (e.g. three).",
        "count: 3",
        "label: null",
        "# Sizes (px; ORB-SLAM: 1, 2).",
        "sizes: [1, 2]",
        "# A nested config.",
        "inner:",
        "  # Radius (m).",
        "  radius: 1.0",
    ]
    assert undocumented_fields(Outer()) == ["label"]
    assert field_docs(Inner)["radius"].comment_lines == 2
    path = tmp_path / "outer.yaml"
    path.write_text(render_yaml(Outer(count=5, label="a: b", sizes=())))
    assert load_config(Outer, path) == Outer(count=5, label="a: b", sizes=())


@pytest.mark.parametrize("section", SECTIONS, ids=lambda s: s.name)
def test_section_round_trip(section, tmp_path: Path) -> None:
    """The YAML a section prints loads back into its defaults."""
    path = tmp_path / f"{section.name}.yaml"
    path.write_text(render_section(section), encoding="utf-8")
    assert load_config(section.config_class(), path) == section.defaults()


def test_sections_cover_the_registries() -> None:
    names = {section.name for section in SECTIONS}
    assert set(LOOP_DETECTORS._builtins) <= names
    assert set(OBJECT_DETECTORS._builtins) - {"none"} <= names  # none has no settings


@pytest.mark.parametrize("name", sorted(LOOP_DETECTORS._builtins))
def test_loop_detector_sections_match_their_factories(name: str) -> None:
    """A section's defaults are the config its registered factory builds (e.g. flat: graph.tiers 1)."""
    detector = LOOP_DETECTORS.load(name)()
    assert detector.config == find_section(name).defaults()  # type: ignore[attr-defined]


def test_every_field_has_a_comment() -> None:
    missing: dict[str, str] = {}
    for section in SECTIONS:
        config = section.defaults()
        for dotted in undocumented_fields(config):
            *path, name = dotted.split(".")
            owner = config
            for part in path:
                owner = getattr(owner, part)
            doc = field_docs(type(owner))[name]
            missing[f"{type(owner).__name__}.{name}"] = f"{doc.file}:{doc.line}"
    unexpected = {key: where for key, where in missing.items() if key not in KNOWN_UNDOCUMENTED}
    assert not unexpected, "config fields without a `#:` comment above them: " + ", ".join(
        f"{key} ({where})" for key, where in sorted(unexpected.items())
    )


def _config_classes() -> list[type]:
    """Every config class the sections reach, nested configs included."""
    found: list[type] = []

    def walk(config: Any) -> None:
        if type(config) not in found:
            found.append(type(config))
        for f in dataclasses.fields(config):
            value = getattr(config, f.name)
            if dataclasses.is_dataclass(value) and not isinstance(value, type):
                walk(value)

    for section in SECTIONS:
        walk(section.defaults())
    return found


def _multi_line_comments(classes: list[type]) -> list[str]:
    return [
        f"{cls.__name__}.{name} ({doc.file}:{doc.line}, {doc.comment_lines} lines)"
        for cls in classes
        for name, doc in field_docs(cls).items()
        if doc.comment_lines > 1
    ]


def test_every_field_comment_is_one_line() -> None:
    """One ``#:`` line per config field: the evidence behind a value goes to a dated note under docs/
    (docs/2026-12-06-config-evidence.md)."""
    assert [entry.split(" ")[0] for entry in _multi_line_comments([Outer, Inner])] == ["Inner.radius"]
    long = _multi_line_comments(_config_classes())
    assert not long, "config field comments longer than one `#:` line: " + ", ".join(long)


def test_config_frontend_prints_commented_yaml(capsys: pytest.CaptureFixture[str]) -> None:
    assert symbio(["config", "frontend"]) == 0
    out = capsys.readouterr().out
    assert "\norb:\n" in out
    lines = out.splitlines()
    assert lines[0].startswith("# == frontend")
    fields = [i for i, line in enumerate(lines) if re.match(r"^\s*\w+:", line)]
    assert len(fields) > 100
    uncommented = [lines[i] for i in fields if not lines[i - 1].lstrip().startswith("# ")]
    assert not uncommented
    assert all(not line.lstrip().startswith("#:") for line in lines)


def test_config_all_sections_and_list(capsys: pytest.CaptureFixture[str]) -> None:
    assert symbio(["config"]) == 0
    out = capsys.readouterr().out
    for section in SECTIONS:
        assert f"# == {section.name}: " in out
    assert symbio(["config", "--list"]) == 0
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines()]
    assert listed == [section.name for section in SECTIONS]


def test_unknown_section_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert symbio(["config", "no-such-part"]) == 2
    err = capsys.readouterr().err
    assert "unknown config section 'no-such-part'" in err
    assert "known: frontend, replay, symbiolcd2" in err
    with pytest.raises(ConfigError):
        find_section("no-such-part")


#: Sections whose config modules load none of gtsam, pycolmap and onnxruntime. ``frontend`` is not
#: one: ``frontends/mono_vo/__init__.py`` imports the frontend (local BA: gtsam) with its config.
LIGHT_SECTIONS = ("orb", "replay", "symbiolcd2", "symbiolcd", "vbow", "ssd-mobilenet", "oracle")


def test_light_sections_load_no_heavy_libraries() -> None:
    code = (
        "import sys; from eval.cli import main\n"
        "main(['config', '--list'])\n"
        f"for name in {LIGHT_SECTIONS!r}: main(['config', name])\n"
        "print(sorted(m for m in ('gtsam', 'pycolmap', 'onnxruntime') if m in sys.modules))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO_ROOT)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-1] == "[]"


def test_docs_config_md_is_current() -> None:
    assert CONFIG_MD.is_file(), f"docs/config.md is missing; regenerate it: {REGENERATE}"
    assert CONFIG_MD.read_text(encoding="utf-8") == render_markdown(), (
        f"docs/config.md is out of date with the config dataclasses; regenerate it: {REGENERATE}"
    )
