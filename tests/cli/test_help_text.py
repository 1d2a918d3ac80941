"""No help text loses a bracketed word: every command's `--help` is rendered and every `[...]` of its source strings
must be in it.

Typer renders help with rich markup, where `[timing]` is a style tag and vanishes unless written `\\[timing]`.
The source strings are the click objects' help (command docstrings and option helps) with rich's escapes undone;
the control below shows that the check finds an unescaped word.
"""

from __future__ import annotations

import re
from collections.abc import Iterator

import pytest
import typer
from typer.core import TyperGroup
from typer.testing import CliRunner

from procedures.cli.app import app

BRACKETED = re.compile(r"\[[^\[\]]*\]")
WIDE = {"COLUMNS": "4000"}
"""Wide enough that rich wraps no help line (a word split over two lines would not be found)."""


def _commands(command: typer.core.TyperCommand | TyperGroup, path: tuple[str, ...] = ()) -> Iterator[tuple]:
    yield path, command
    if isinstance(command, TyperGroup):
        for name, sub in command.commands.items():
            yield from _commands(sub, (*path, name))


def _source_strings(command: typer.core.TyperCommand | TyperGroup) -> list[str]:
    """The help strings as written, rich's escapes undone: the command's, its parameters', its sub-commands'."""
    strings = [command.help or "", *(getattr(p, "help", None) or "" for p in command.params)]
    if isinstance(command, TyperGroup):  # the group's listing shows each sub-command's first paragraph
        strings += [(sub.help or "").split("\n\n")[0] for sub in command.commands.values()]
    return [s.replace("\\[", "[") for s in strings]


def lost_words(application: typer.Typer) -> tuple[set[str], dict[str, list[str]]]:
    """The bracketed words checked, and per `hilcal ... --help` those its rendered help does not show."""
    runner = CliRunner()
    checked: set[str] = set()
    lost = {}
    for path, command in _commands(typer.main.get_command(application)):
        result = runner.invoke(application, [*path, "--help"], env=WIDE)
        assert result.exit_code == 0, result.output
        shown = " ".join(result.output.split())
        words = {" ".join(w.split()) for s in _source_strings(command) for w in BRACKETED.findall(s)}
        checked |= words
        missing = sorted(w for w in words if w not in shown)
        if "\\[" in shown:
            missing.append("a rich escape shown as a backslash")
        if missing:
            lost[" ".join(path) or "(app)"] = missing
    return checked, lost


def test_every_help_text_keeps_its_bracketed_words() -> None:
    checked, lost = lost_words(app)
    assert lost == {}
    assert {"[timing]", "[modbus]"} <= checked  # the words the issue found missing are among those checked


def test_the_check_finds_an_unescaped_word() -> None:
    """The control: an option help with a bare `[timing]` loses it; escaped, it is kept."""
    demo = typer.Typer(add_completion=False)

    @demo.command()
    def one(station: str = typer.Option("", help="only its [timing] is used")) -> None:
        """Run [quickly]."""

    @demo.command()
    def two(station: str = typer.Option("", help="only its \\[timing] is used")) -> None:
        """Run \\[quickly]."""

    assert lost_words(demo) == ({"[quickly]", "[timing]"}, {"one": ["[quickly]", "[timing]"]})



@pytest.mark.slow
def test_a_printed_message_keeps_its_bracketed_words(tmp_path) -> None:
    """Printed messages too: markup is off on the consoles, so a path with `[lab]` in it is printed whole."""
    folder = tmp_path / "[lab] rig"
    folder.mkdir()
    result = CliRunner().invoke(app, ["simulate", "--out", str(folder / "rec.csv"), "--seed", "1"], env=WIDE)
    assert result.exit_code == 0, result.output
    assert f"wrote{folder / 'rec.csv'}".replace(" ", "") in "".join(result.output.split())  # however rich wraps it
