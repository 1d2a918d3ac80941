"""How `hilcal ... --help` is laid out: whole words at any width, whole paragraphs, every option on its own line.

Typer's rich help puts options in a table whose narrow columns cut long words and names with an ellipsis at 80
columns. Here each option's names come on one line and its help below, across the width; a word longer than the
line is folded, never cut. Help strings keep rich markup (``\\[timing]`` is the word ``[timing]``).
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Iterable
from typing import Any

import typer
from rich.console import Console, Group
from rich.padding import Padding
from rich.table import Table
from rich.text import Text
from typer.core import TyperCommand, TyperGroup

INDENT = 6
"""Columns an option's or a command's help is indented by under its name."""


def paragraphs(text: str | None) -> list[str]:
    """A docstring's paragraphs, each on one line (a paragraph that starts with \\b keeps its line breaks)."""
    out = []
    for block in inspect.cleandoc(text or "").partition("\f")[0].split("\n\n"):
        if block.startswith("\b"):
            out.append(block.removeprefix("\b").strip("\n"))
        elif block.strip():
            out.append(" ".join(block.split()))
    return out


def _console() -> Console:
    width = os.environ.get("TERMINAL_WIDTH")  # typer's own setting, honoured as typer does
    return Console(width=int(width) if width else None, highlight=False, soft_wrap=False)


def _option(param: Any, ctx: typer.Context) -> Group | None:
    """An option's names (and value) on one line, its help with default, range and 'required' indented below."""
    record = param.get_help_record(ctx)
    if record is None:
        return None
    names, help_with_extras = record
    help_text = " ".join((getattr(param, "help", None) or "").split())
    extras = " ".join(help_with_extras.split())
    extras = extras[len(help_text):].strip() if extras.startswith(help_text) else ""
    body = Text.from_markup(help_text) if help_text else Text()
    if extras:
        body.append(("  " if help_text else "") + extras, style="dim")
    return Group(Text("  " + names, style="bold"), Padding(body, (0, 0, 0, INDENT), expand=False))


def _commands(group: TyperGroup, ctx: typer.Context) -> Table:
    """Each sub-command with the first paragraph of its help; a long description wraps in its own column."""
    table = Table.grid(padding=(0, 2))
    names = [n for n in group.list_commands(ctx) if not group.commands[n].hidden]
    table.add_column(no_wrap=True, min_width=max((len(n) for n in names), default=0) + 2)
    table.add_column(overflow="fold", ratio=1)
    for name in names:
        first = (paragraphs(group.commands[name].help) or [""])[0]
        table.add_row(Text("  " + name, style="bold"), Text.from_markup(first))
    return table


def render_help(command: TyperCommand | TyperGroup, ctx: typer.Context) -> None:
    """Print the help of a command or group: usage, description, options (and sub-commands)."""
    console = _console()
    console.print(Text(f"Usage: {command.get_usage(ctx).removeprefix('Usage: ')}"), overflow="fold")
    for text in paragraphs(command.help):
        console.print()
        console.print(Text.from_markup(text), overflow="fold")
    sections: list[tuple[str, Iterable]] = []
    arguments = [p for p in command.get_params(ctx) if p.param_type_name == "argument"]
    options = [p for p in command.get_params(ctx) if p.param_type_name == "option"]
    for title, params in (("Arguments", arguments), ("Options", options)):
        shown = [item for p in params if (item := _option(p, ctx)) is not None]
        if shown:
            sections.append((title, shown))
    if isinstance(command, TyperGroup) and command.commands:
        sections.append(("Commands", [_commands(command, ctx)]))
    for title, items in sections:
        console.print()
        console.print(Text(f"{title}:", style="bold underline"))
        for item in items:
            console.print(item, overflow="fold")


class HelpCommand(TyperCommand):
    """A `hilcal` command whose help keeps every word whole (``render_help``)."""

    def format_help(self, ctx: typer.Context, formatter: object) -> None:
        render_help(self, ctx)


class HelpGroup(TyperGroup):
    """A `hilcal` group whose help keeps every word whole and lists every command (``render_help``)."""

    def format_help(self, ctx: typer.Context, formatter: object) -> None:
        render_help(self, ctx)
