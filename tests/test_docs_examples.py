"""The shell examples of the documentation parse as they are written.

Every ``ipc-component ...`` and ``python -m component_container ...`` command in a code block of README.md and
docs/ (``$ `` lines of console blocks, the lines of shell blocks, ``\\``-continued) goes through the real argument
parser of its program, so an option that does not exist (``ipc-component load ... --use-intra-process-comms``, a
container option) fails here, naming the file and line. Synopses (``<bag>``, ``[options]``, ``a|b``) are not
examples and are left out. No ROS is started.
"""
from __future__ import annotations

import contextlib
import io
import pathlib
import re
import shlex
from dataclasses import dataclass

import pytest

from component_container.__main__ import parse_arguments
from ipc_component.cli import build_parser, split_ros_args

REPO = pathlib.Path(__file__).resolve().parents[1]
FENCE = re.compile(r"^```(?P<language>\w*)\n(?P<body>.*?)^```", re.MULTILINE | re.DOTALL)
PROGRAMS = (("ipc-component",), ("python", "-m", "component_container"))
#: Where a command line ends for the shell.
SHELL_OPERATORS = {">", ">>", "2>&1", "&", "|", ";", "&&", "||"}


@dataclass(frozen=True)
class Example:
    """One command of a code block: where it is, and its words (the program's name first)."""

    where: str
    words: tuple[str, ...]

    def __str__(self) -> str:
        return f"{self.where}: {shlex.join(self.words)}"


def examples() -> list[Example]:
    """Every example command of the documentation, in file order."""
    found = []
    for path in [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]:
        text = path.read_text()
        for fence in FENCE.finditer(text):
            first_line = text.count("\n", 0, fence.start("body")) + 1
            for offset, line in _commands(fence["body"], console=fence["language"] == "console"):
                words = _words(line)
                if words is not None:
                    found.append(Example(f"{path.relative_to(REPO)}:{first_line + offset}", words))
    return found


def _commands(body: str, console: bool) -> list[tuple[int, str]]:
    """(line offset, command) of a block's commands, continuation lines joined; in a console block only the
    lines after a ``$`` prompt are commands."""
    commands: list[tuple[int, str]] = []
    lines = body.splitlines()
    index = 0
    while index < len(lines):
        start, line = index, lines[index]
        while line.endswith("\\") and index + 1 < len(lines):
            index += 1
            line = line[:-1] + " " + lines[index]
        index += 1
        if console and not line.startswith("$ "):
            continue
        commands.append((start, line.removeprefix("$ ")))
    return commands


def _words(line: str) -> tuple[str, ...] | None:
    """The command's words (without environment assignments before it and shell redirections after it), or None
    for a line that runs none of the programs, or is a synopsis."""
    try:
        words = shlex.split(line, comments=True)
    except ValueError:
        return None
    while words and re.fullmatch(r"[A-Za-z_]\w*=\S*", words[0]):
        words = words[1:]
    end = next((index for index, word in enumerate(words) if word in SHELL_OPERATORS), len(words))
    words = words[:end]
    if not any(tuple(words[:len(program)]) == program for program in PROGRAMS):
        return None
    if any(word[:1] in "<[({" or "|" in word or "..." in word for word in words):
        return None  # a synopsis, not an example
    return tuple(words)


ALL = examples()


def test_the_documentation_has_examples_of_both_programs() -> None:
    assert sum(example.words[0] == "ipc-component" for example in ALL) >= 40, [str(e) for e in ALL]
    assert sum(example.words[0] == "python" for example in ALL) >= 5, [str(e) for e in ALL]


def test_the_synopses_are_not_taken_for_examples() -> None:
    assert _words("ipc-component bag info <bag> [-t] [-v] [--sort {name,type,count}]") is None
    assert _words("ipc-component load /C components components::Recorder -p 'a:=[1, 2]' -e x:=true") is not None
    assert _words("PYTHONPATH=examples python -m component_container --low-latency > c.log 2>&1 &") == (
        "python", "-m", "component_container", "--low-latency")


@pytest.mark.parametrize("example", ALL, ids=str)
def test_every_example_parses_with_its_programs_parser(example: Example, tmp_path: pathlib.Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    errors = io.StringIO()
    with contextlib.redirect_stderr(errors):
        try:
            if example.words[0] == "ipc-component":
                build_parser().parse_args(split_ros_args(list(example.words[1:]))[0])
            else:
                monkeypatch.chdir(tmp_path)  # the --bag-root an example names must exist: made here
                if "--bag-root" in example.words:
                    (tmp_path / example.words[example.words.index("--bag-root") + 1]).mkdir(parents=True)
                parse_arguments(["component_container", *example.words[3:]])
        except SystemExit as exit_:
            pytest.fail(f"{example}\nis refused by the parser (exit {exit_.code}): {errors.getvalue().strip()}")
