"""Every command README.md and the notes in docs/*.md show must work as written.

* ``symbio ...`` in fenced ``bash``/``sh``/``shell``/``console`` blocks: the full argv parses with
  ``eval.cli.build_parser()`` (argparse only: no handler runs, no file is read or written; paths in
  the commands need not exist), and ``symbio SUBCOMMAND --help`` exits 0. Inline code spans that
  call ``symbio`` with options (``symbio posegraph --trajectory ...``) parse too; being prose
  fragments, they may leave out required arguments, nothing else.
* ``python -m PACKAGE.MODULE ...`` / ``python path/to/script.py ...`` of this project (fenced or
  inline): the module or script exists, ``--help`` exits 0 and lists every option the command uses.
  Names with an all-capitals placeholder (``eval.bench.NAME``) are not commands and are skipped.
* ``make TARGET ...``: every target is a rule of the Makefile.

Fenced lines may end in ``# comments`` and continue with ``\\``; ``console`` blocks mark commands
with a ``$ `` prompt. Tests are parametrised by file and line (``README.md:12:symbio demo ...``,
``docs/slam-runs.md:872:symbio run ...``), so a failure names both. The tests at the end feed broken
README texts to the same checks and expect them to fail.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import importlib.util
import io
import json
import re
import shlex
import subprocess
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import pytest

from eval.cli import build_parser

REPO_ROOT = Path(__file__).resolve().parent.parent
README = REPO_ROOT / "README.md"
DOCS = REPO_ROOT / "docs"
MAKEFILE = REPO_ROOT / "Makefile"

SHELL_LANGUAGES = frozenset({"bash", "sh", "shell", "console", "zsh"})
PROJECT_PACKAGES = frozenset({"eval", "frontends", "lcd", "slam_backend"})
SEPARATORS = frozenset({"&&", "||", ";", "|", "&"})
REDIRECTIONS = frozenset({">", ">>", "<", ">&", "&>", ">|", "<<"})
HELP_TIMEOUT_S = 180


class ReadmeCommandError(AssertionError):
    """A README (or docs/) command that does not work as written."""


@dataclass(frozen=True)
class ReadmeCommand:
    #: 1-based line of ``source`` where the command starts.
    line: int
    #: The command as written (continuation lines joined, comments kept).
    text: str
    #: Its words (quotes removed, comments dropped), one simple command of a ``&&``/``;``/``|`` chain.
    argv: tuple[str, ...]
    #: From a fenced block (a complete command), or an inline code span (may be a fragment).
    fenced: bool
    #: The markdown file it comes from, relative to the repository ("README", "docs/slam-runs.md").
    source: str = "README"

    @property
    def program(self) -> str:
        name = Path(self.argv[0]).name
        if name == "symbio":
            return "symbio"
        if name == "make":
            return "make"
        if re.fullmatch(r"python(3(\.\d+)?)?", name):
            return "python"
        return name

    def fail(self, problem: str) -> ReadmeCommandError:
        kind = "fenced block" if self.fenced else "inline code"
        return ReadmeCommandError(f"{self.source} line {self.line} ({kind}) `{self.text}`: {problem}")


# ------------------------------------------------------------------------------------ extraction
def simple_commands(text: str) -> list[list[str]]:
    """Shell words of ``text``, split at ``&&``, ``;``, ``|`` ...; redirections, comments and leading
    ``NAME=value`` assignments dropped. Unbalanced quotes raise ValueError."""
    lexer = shlex.shlex(text, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    commands: list[list[str]] = [[]]
    words = list(lexer)
    skip = False
    for k, word in enumerate(words):
        if skip:
            skip = False
        elif word in SEPARATORS:
            commands.append([])
        elif word in REDIRECTIONS:
            skip = True  # and its target
        elif word.isdigit() and k + 1 < len(words) and words[k + 1] in REDIRECTIONS:
            pass  # the file descriptor of "2>"
        elif not commands[-1] and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", word):
            pass  # an environment assignment before the program
        else:
            commands[-1].append(word)
    return [command for command in commands if command]


def fenced_shell_lines(markdown: str) -> Iterator[tuple[int, str]]:
    """(line, command text) of each command in the fenced shell blocks, continuations joined."""
    lines = markdown.splitlines()
    fence: str | None = None
    language = ""
    pending: tuple[int, str] | None = None
    for number, raw in enumerate(lines, start=1):
        stripped = raw.strip()
        if fence is None:
            opening = re.match(r"^ {0,3}(`{3,}|~{3,})\s*([^\s`]*)", raw)
            if opening:
                fence, language = opening.group(1), opening.group(2).lower()
            continue
        if stripped.startswith(fence) and not stripped.strip(fence[0]):
            fence, pending = None, None
            continue
        if language not in SHELL_LANGUAGES:
            continue
        if pending is not None:  # the continuation of the previous line
            start, text = pending
            text = f"{text} {stripped}"
        elif language == "console":
            if not stripped.startswith("$ "):
                continue  # output, not a command
            start, text = number, stripped[2:]
        else:
            start, text = number, stripped.removeprefix("$ ")
        if text.endswith("\\"):
            pending = (start, text[:-1].rstrip())
            continue
        pending = None
        if text and not text.startswith("#"):
            yield start, text


def inline_code_spans(markdown: str) -> Iterator[tuple[int, str]]:
    """(line, text) of each inline code span outside fenced blocks (a span may wrap a line)."""
    kept = []
    fence: str | None = None
    for raw in markdown.splitlines():
        opening = re.match(r"^ {0,3}(`{3,}|~{3,})", raw)
        if fence is None and opening:
            fence = opening.group(1)
            kept.append("")
        elif fence is not None:
            if raw.strip().startswith(fence) and not raw.strip().strip(fence[0]):
                fence = None
            kept.append("")
        else:
            kept.append(raw)
    text = "\n".join(kept)
    for span in re.finditer(r"(?<!`)(`+)(?!`)(.+?)(?<!`)\1(?!`)", text, re.DOTALL):
        if "\n\n" in span.group(2):
            continue  # not a span: markdown code spans never cross paragraphs
        yield text.count("\n", 0, span.start()) + 1, " ".join(span.group(2).split())


def readme_commands(markdown: str, source: str = "README") -> list[ReadmeCommand]:
    """Every ``symbio``, project ``python`` and ``make`` command in ``markdown`` (the file ``source``)."""
    found: list[ReadmeCommand] = []
    sources = [(line, text, True) for line, text in fenced_shell_lines(markdown)]
    sources += [(line, text, False) for line, text in inline_code_spans(markdown)]
    for line, text, fenced in sources:
        try:
            commands = simple_commands(text)
        except ValueError as exc:  # unbalanced quotes
            if fenced:
                broken = ReadmeCommand(line, text, ("?",), fenced, source)
                raise broken.fail(f"not a shell command ({exc})") from None
            continue
        for argv in commands:
            command = ReadmeCommand(line, text, tuple(argv), fenced, source)
            wanted = {
                "symbio": fenced or any(word.startswith("-") for word in argv[1:]),
                "python": python_target(command) is not None,
                "make": True,
            }
            if wanted.get(command.program, False):
                found.append(command)
    return found


# ------------------------------------------------------------------------------------ checks
def parse_symbio(args: list[str]) -> tuple[int | None, str]:
    """Parse ``symbio ARGS`` with the real parser: (exit code, or None when it parsed; its output)."""
    parser = build_parser()
    output = io.StringIO()
    with contextlib.redirect_stdout(output), contextlib.redirect_stderr(output):
        try:
            parser.parse_args(args)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            return code, output.getvalue()
    return None, output.getvalue()


def subparsers_of(parser: argparse.ArgumentParser) -> argparse._SubParsersAction | None:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action
    return None


def subcommand_path(args: list[str]) -> list[str]:
    """The subcommand words of ``symbio ARGS`` (``["eval", "lcd"]``), options skipped."""
    parser, path = build_parser(), []
    for word in args:
        if word.startswith("-"):
            continue
        subparsers = subparsers_of(parser)
        if subparsers is None or word not in subparsers.choices:
            break
        path.append(word)
        parser = subparsers.choices[word]
    return path


def unlisted_options(words: Sequence[str], help_text: str) -> list[str]:
    """The ``-x`` / ``--option`` words (``--option=value`` too) that ``help_text`` does not mention."""
    options = [word.split("=", 1)[0] for word in words]
    return [
        option
        for option in options
        if re.fullmatch(r"--?[A-Za-z][\w-]*", option)
        and not re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", help_text)
    ]


def check_symbio(command: ReadmeCommand) -> None:
    args = list(command.argv[1:])
    code, output = parse_symbio(args)
    # An inline fragment may leave out required arguments (argparse then stops before it looks at
    # unknown options, so those are checked against the help below).
    fragment = not command.fenced and "the following arguments are required" in output
    if code not in (None, 0) and not fragment:
        raise command.fail(f"`symbio` rejects it (exit {code}):\n{output.strip()}")
    path = subcommand_path(args)
    code, help_text = parse_symbio([*path, "--help"])
    if code != 0 or "usage:" not in help_text:
        raise command.fail(f"`symbio {' '.join(path)} --help` exits {code}:\n{help_text.strip()}")
    unknown = unlisted_options(args, help_text)
    if fragment and unknown:
        raise command.fail(f"`symbio {' '.join(path)} --help` does not list {', '.join(unknown)}")


def python_target(command: ReadmeCommand) -> tuple[str, str] | None:
    """("module", "eval.bench.lcd") or ("script", "eval/bench/synth.py") for commands of this
    project; None for other python commands and for placeholders (``eval.bench.NAME``)."""
    argv = command.argv
    if len(argv) >= 3 and argv[1] == "-m":
        target = ("module", argv[2]) if argv[2].split(".")[0] in PROJECT_PACKAGES else None
    elif len(argv) >= 2 and argv[1].endswith(".py") and not Path(argv[1]).is_absolute():
        target = ("script", argv[1])
    else:
        target = None
    if target is None or re.search(r"[A-Z]{2,}", target[1]):
        return None
    return target


# Runs ``--help`` of many modules and scripts in one interpreter, so the heavy imports they share
# (gtsam, OpenCV, pycolmap) are paid once: prints one JSON object {"kind:target": [exit code, output]}.
HELP_BATCH = """
import contextlib, io, json, runpy, sys, warnings
warnings.filterwarnings("ignore", "'.*' found in sys.modules", RuntimeWarning)  # run twice: harmless
results = {}
for kind, target in json.loads(sys.argv[1]):
    output, code = io.StringIO(), -2
    sys.argv = [target, "--help"]
    try:
        with contextlib.redirect_stdout(output), contextlib.redirect_stderr(output):
            if kind == "module":
                runpy.run_module(target, run_name="__main__", alter_sys=True)
            else:
                runpy.run_path(target, run_name="__main__")
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except BaseException:
        pass
    results[kind + ":" + target] = [code, output.getvalue()]
sys.stdout = sys.__stdout__
print(json.dumps(results))
"""


@functools.cache
def batched_python_help() -> dict[str, tuple[int, str]]:
    """``--help`` of every python command of the README and docs/, from one process; only clean
    results (exit 0 with a usage line) are kept: anything else is redone alone by python_help."""
    targets = sorted({target for command in ALL_COMMANDS if (target := python_target(command))})
    try:
        result = subprocess.run(
            [sys.executable, "-c", HELP_BATCH, json.dumps(targets)],
            cwd=REPO_ROOT, capture_output=True, text=True, timeout=HELP_TIMEOUT_S,
        )  # fmt: skip
        found = json.loads(result.stdout.strip().splitlines()[-1]) if result.returncode == 0 else {}
    except (subprocess.TimeoutExpired, ValueError, IndexError):
        found = {}
    return {key: (code, text) for key, (code, text) in found.items() if code == 0 and "usage:" in text}


@functools.cache
def python_help(kind: str, target: str) -> tuple[int, str]:
    """Exit code and output of ``python -m MODULE --help`` / ``python SCRIPT --help``."""
    batched = batched_python_help().get(f"{kind}:{target}")
    if batched is not None:
        return batched
    run = [sys.executable, "-m", target] if kind == "module" else [sys.executable, target]
    try:
        result = subprocess.run(
            [*run, "--help"], cwd=REPO_ROOT, capture_output=True, text=True, timeout=HELP_TIMEOUT_S
        )
    except subprocess.TimeoutExpired:
        return -1, f"--help did not finish within {HELP_TIMEOUT_S} s"
    return result.returncode, result.stdout + result.stderr


def check_python(command: ReadmeCommand) -> None:
    target = python_target(command)
    assert target is not None
    kind, name = target
    if kind == "module":
        try:
            exists = importlib.util.find_spec(name) is not None
        except ImportError:
            exists = False
        if not exists:
            raise command.fail(f"no module {name!r}")
        options = command.argv[3:]
    else:
        if not (REPO_ROOT / name).is_file():
            raise command.fail(f"no script {name} in the repository")
        options = command.argv[2:]
    code, output = python_help(kind, name)
    if code != 0:
        raise command.fail(f"`{name} --help` exits {code}:\n{output[-2000:]}")
    unknown = unlisted_options(options, output)
    if unknown:
        raise command.fail(f"`{name} --help` does not list the option {', '.join(unknown)}")


@functools.cache
def makefile_targets() -> frozenset[str]:
    targets: set[str] = set()
    for raw in MAKEFILE.read_text(encoding="utf-8").splitlines():
        if raw.startswith(("\t", "#")):
            continue
        rule = re.match(r"^([^:=#\s][^:=#]*?)\s*::?(?!=)", raw)
        if rule:
            names = rule.group(1).split()
            targets.update(name for name in names if not name.startswith(".") and not {"$", "%"} & set(name))
    return frozenset(targets)


def check_make(command: ReadmeCommand) -> None:
    goals = [word for word in command.argv[1:] if not word.startswith("-") and "=" not in word]
    missing = [goal for goal in goals if goal not in makefile_targets()]
    if missing:
        raise command.fail(f"no Makefile target {', '.join(missing)} (targets: {sorted(makefile_targets())})")


def check_command(command: ReadmeCommand) -> None:
    {"symbio": check_symbio, "python": check_python, "make": check_make}[command.program](command)


def check_readme_text(markdown: str, source: str = "README") -> int:
    """Check every command of ``markdown``; raises ReadmeCommandError at the first broken one."""
    commands = readme_commands(markdown, source)
    for command in commands:
        check_command(command)
    return len(commands)


# ------------------------------------------------------------------------------------ the README and docs/
DOCS_FILES = sorted(DOCS.glob("*.md"))


def file_commands(path: Path) -> list[ReadmeCommand]:
    source = path.relative_to(REPO_ROOT).as_posix()
    return readme_commands(path.read_text(encoding="utf-8"), source=source)


README_COMMANDS = file_commands(README) if README.is_file() else []
DOCS_COMMANDS = [command for path in DOCS_FILES for command in file_commands(path)]


def by_program(program: str, commands: Sequence[ReadmeCommand] = README_COMMANDS) -> list[ReadmeCommand]:
    return [command for command in commands if command.program == program]


def command_id(command: ReadmeCommand) -> str:
    return f"{command.source}:{command.line}:{' '.join(command.argv)[:60]}"


def test_readme_has_commands() -> None:
    """Guards the extraction itself: the README does show symbio and make commands."""
    assert by_program("symbio"), "no `symbio` command found in README.md's fenced shell blocks"
    assert by_program("make")


def test_docs_have_commands() -> None:
    """Guards the extraction from docs/: the notes that hold the measurements show how they were made."""
    assert DOCS_FILES, f"no markdown files in {DOCS}"
    assert by_program("symbio", DOCS_COMMANDS), "no `symbio` command found in docs/*.md"
    assert by_program("python", DOCS_COMMANDS), "no `python -m eval...` command found in docs/*.md"
    assert {command.source for command in DOCS_COMMANDS} >= {"docs/slam-runs.md", "docs/paper-experiments.md"}


ALL_COMMANDS = [*README_COMMANDS, *DOCS_COMMANDS]


@pytest.mark.parametrize("command", by_program("symbio", ALL_COMMANDS), ids=command_id)
def test_symbio_command(command: ReadmeCommand) -> None:
    check_symbio(command)


@pytest.mark.parametrize("command", by_program("python", ALL_COMMANDS), ids=command_id)
def test_python_command(command: ReadmeCommand) -> None:
    check_python(command)


@pytest.mark.parametrize("command", by_program("make", ALL_COMMANDS), ids=command_id)
def test_make_command(command: ReadmeCommand) -> None:
    check_make(command)


def test_installed_symbio_script_runs() -> None:
    """The README's commands go through the installed console script: it must start."""
    script = Path(sys.executable).with_name("symbio")
    if not script.is_file():
        pytest.skip(f"no console script at {script} (project not installed in this interpreter)")
    result = subprocess.run([str(script), "--help"], capture_output=True, text=True, timeout=HELP_TIMEOUT_S)
    assert result.returncode == 0, result.stderr
    for command in by_program("symbio", ALL_COMMANDS):
        path = subcommand_path(list(command.argv[1:]))
        if path:
            assert path[0] in result.stdout, f"`symbio --help` does not list {path[0]}"


# ------------------------------------------------------------------------------------ the checks fail
def test_extraction_of_fenced_and_inline_commands() -> None:
    markdown = "\n".join(
        [
            "Intro `symbio eval lcd` and `python -m eval.bench.lcd --detectors vbow --sweep",
            "KEY=V1,V2` wraps.",
            "```bash",
            "symbio eval lcd scene \\",
            "    --detector vbow   # a comment",
            "SYMBIO_SHARED=/x make test-shared && symbio detectors | tee out.txt 2> err.txt",
            "# a comment line",
            "```",
            "```console",
            "$ symbio --help",
            "usage: symbio ...",
            "```",
            "```",
            "symbio not-shell-language",
            "```",
        ]
    )
    commands = [(c.line, c.argv, c.fenced) for c in readme_commands(markdown)]
    assert commands == [
        (4, ("symbio", "eval", "lcd", "scene", "--detector", "vbow"), True),
        (6, ("make", "test-shared"), True),
        (6, ("symbio", "detectors"), True),
        (10, ("symbio", "--help"), True),
        (1, ("python", "-m", "eval.bench.lcd", "--detectors", "vbow", "--sweep", "KEY=V1,V2"), False),
    ]


BROKEN_READMES = [
    pytest.param(
        "Text.\n\n```bash\nsymbio eval lcd scene --no-such-flag 3\n```\n",
        "README line 4 .*--no-such-flag",
        id="bogus-flag",
    ),
    pytest.param(
        "```sh\nsymbio evaluate lcd scene --detector vbow   # renamed\n```\n",
        "README line 2 .*invalid choice: 'evaluate'",
        id="renamed-subcommand",
    ),
    pytest.param(
        "```bash\nsymbio eval lcd-eval scene\n```\n",
        "README line 2 .*invalid choice: 'lcd-eval'",
        id="renamed-sub-subcommand",
    ),
    pytest.param(
        "```bash\nsymbio synth --trajectory spiral \\\n  --out scene\n```\n",
        "README line 2 .*spiral",
        id="bad-choice-on-continuation-line",
    ),
    pytest.param(
        "```bash\nsymbio eval lcd --detector vbow\n```\n",
        "README line 2 .*required",
        id="missing-positional",
    ),
    pytest.param(
        "```console\n$ symbio demo --out x --frames\n```\n",
        "README line 2 .*--frames",
        id="console-unknown-option",
    ),
    pytest.param(
        "Run `symbio eval lcd --bogus-option` on it.\n",
        "README line 1 \\(inline code\\).*--bogus-option",
        id="inline-fragment-unknown-option",
    ),
    pytest.param(
        "Run `python -m eval.no_such_module --json x`.\n",
        "no module 'eval.no_such_module'",
        id="python-missing-module",
    ),
    pytest.param(
        "Run `python eval/no_such_script.py`.\n",
        "no script eval/no_such_script.py",
        id="python-missing-script",
    ),
    pytest.param(
        "```bash\nmake demo no-such-target\n```\n",
        "README line 2 .*no Makefile target no-such-target",
        id="make-missing-target",
    ),
]


@pytest.mark.parametrize(("markdown", "message"), BROKEN_READMES)
def test_broken_readme_commands_fail(markdown: str, message: str) -> None:
    with pytest.raises(ReadmeCommandError, match=f"(?s){message}"):
        check_readme_text(markdown)


def test_broken_docs_command_names_its_file() -> None:
    markdown = "Measured (`python -m eval.bench.lcd --json out.json --retired-option 3`).\n"
    with pytest.raises(ReadmeCommandError, match=r"^docs/note\.md line 1 \(inline code\).*--retired-option"):
        check_readme_text(markdown, source="docs/note.md")


def test_python_command_with_an_unknown_option_fails() -> None:
    module = "eval.bench.lcd"
    check_readme_text(f"Run `python -m {module} --json out.json`.")
    with pytest.raises(ReadmeCommandError, match="does not list the option --no-such-option"):
        check_readme_text(f"Run `python -m {module} --json out.json --no-such-option`.")


def test_valid_commands_and_fragments_pass(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Paths need not exist, inline fragments may omit required arguments, and nothing runs: the
    handlers of `symbio demo` / `symbio synth` would write their output folders."""
    monkeypatch.chdir(tmp_path)
    markdown = "\n".join(
        [
            "```bash",
            "symbio demo --out demo_here   # would render a scene",
            "symbio synth --trajectory loop --frames 300 --out scene_here \\",
            "  --contact-sheet sheet.png",
            "symbio eval lcd missing/folder --detector vbow,symbiolcd2 --set iterations=5",
            "make test",
            "```",
            "Inline: `symbio eval lcd --tolerance 3`, `symbio synth`, `python -m eval.bench.NAME`.",
        ]
    )
    assert check_readme_text(markdown) == 5
    assert list(tmp_path.iterdir()) == []
