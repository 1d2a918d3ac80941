"""Every `hilcal ... --help` at 80 columns: text kept whole (no "…" cut, no line wider than the screen, every help
string found entire), every option described, the command list complete, and nothing written for the tool's
developers (test paths, module names).

The control renders a command with typer's own rich help, whose narrow table columns cut a long word at 80 columns:
the same check finds the cut there.
"""

from __future__ import annotations

import re
from collections.abc import Iterator

import typer
from rich.text import Text
from typer.core import TyperGroup
from typer.testing import CliRunner

from procedures.cli.app import HELP, app
from procedures.cli.help_format import HelpCommand, paragraphs

NARROW = {"COLUMNS": "80"}
DEVELOPER_WORDS = re.compile(r"(?<![/\w])(tests|benchmarks|procedures|sim_devices|drivers|hilcal)[/.][a-z_]|\w\.py\b")
"""A path or module of the source tree (docs/... pages are the user's and may be named)."""


def _commands(command: typer.core.TyperCommand | TyperGroup, path: tuple[str, ...] = ()) -> Iterator[tuple]:
    yield path, command
    if isinstance(command, TyperGroup):
        for name, sub in command.commands.items():
            yield from _commands(sub, (*path, name))


def _plain(markup: str) -> str:
    """A help string as shown: rich markup read (``\\[timing]`` is ``[timing]``), whitespace as single spaces."""
    return " ".join(Text.from_markup(markup).plain.split())


def problems_at_80(application: typer.Typer) -> dict[str, list[str]]:
    """Per `hilcal ... --help`: what is cut, too wide, lost or undescribed at 80 columns."""
    runner = CliRunner()
    found = {}
    for path, command in _commands(typer.main.get_command(application)):
        result = runner.invoke(application, [*path, "--help"], env=NARROW)
        assert result.exit_code == 0, result.output
        shown = " ".join(result.output.split())
        problems = [f"cut: {line.strip()!r}" for line in result.output.splitlines() if "…" in line]
        problems += [f"wider than 80: {line!r}" for line in result.output.splitlines() if len(line.rstrip()) > 80]
        sources = [*paragraphs(command.help), *(p.help for p in command.params if getattr(p, "help", None))]
        problems += [f"not whole: {text[:60]!r}" for text in sources if _plain(text) not in shown]
        problems += [f"no description: {p.opts[0]}" for p in command.params
                     if p.param_type_name == "option" and not getattr(p, "help", None)]
        if problems:
            found[" ".join(path) or "(app)"] = problems
    return found


def test_every_help_is_whole_and_described_at_80_columns() -> None:
    assert problems_at_80(app) == {}


def test_the_check_finds_what_typers_own_table_cuts() -> None:
    """The control: typer's rich table at 80 columns cuts a long word (and the checked help is otherwise complete)."""
    demo = typer.Typer(add_completion=False)
    url = "records database: a file or a URL (postgresql+psycopg://user@host/db), default $HILCAL_RECORDS"

    @demo.command()
    def plain(records_database_location: str = typer.Option("", help=url), panel_linger_minutes: float = typer.Option(
            1.0, help="keep the panel up this long after the run (docs/procedure.md#the-operator-panel)")) -> None:
        """Typer's layout."""

    @demo.command(cls=HelpCommand)
    def ours(records_database_location: str = typer.Option("", help=url), panel_linger_minutes: float = typer.Option(
            1.0, help="keep the panel up this long after the run (docs/procedure.md#the-operator-panel)")) -> None:
        """hilcal's layout."""

    found = problems_at_80(demo)
    assert set(found) == {"plain"} and any(p.startswith("cut: ") for p in found["plain"])


def test_the_app_help_names_every_command() -> None:
    intro = " ".join(HELP.split())
    names = list(typer.main.get_command(app).commands)
    assert len(names) >= 18 and {"check", "certificate", "drift", "records"} <= set(names)
    missing = [name for name in names if not re.search(rf"(?<![\w-]){re.escape(name)}(?![\w-])", intro)]
    assert missing == []


def test_no_help_speaks_to_the_tools_developers() -> None:
    runner = CliRunner()
    said = {}
    for path, _ in _commands(typer.main.get_command(app)):
        output = runner.invoke(app, [*path, "--help"], env={"COLUMNS": "4000"}).output
        hits = sorted({m.group(0) for m in DEVELOPER_WORDS.finditer(output)})
        if hits:
            said[" ".join(path) or "(app)"] = hits
    assert said == {}
    assert DEVELOPER_WORDS.search("imports none of them (tests/cli/test_startup.py)")  # the check sees one
