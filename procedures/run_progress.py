"""How a run shows its progress at the terminal: a bar over the poses, and an adaptive run's decisions as lines.

The bar counts measured poses; an adaptive run does not know its count in advance, so each decision (the
``procedures.adaptive.progress`` checkpoint) prints its prediction and forecast above the bar and sets the bar's total
to the rows so far plus those forecast plus the verify phases'.

The bar is a live display: it redraws its line several times a second, over whatever was written on it. While the
operator reads and answers a question (a prompt with its detail, the pause), the engine holds `bar_aside`: the bar
leaves the screen and comes back below the answer.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Any

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from procedures.adaptive import PROGRESS_LABEL, progress_line
from procedures.messages import Checkpoint

Observer = Callable[[str, dict], None]
PHASES = {"measure": "measure", "verify": "verify before the upload", "verify_after": "verify after the upload",
          "acceptance": "ISO 9283 test"}
"""The journal's phases as the bar names them."""


@contextlib.contextmanager
def terminal_progress(total: int, done: int) -> Iterator[tuple[Callable[[dict], None], Progress, Any]]:
    """The bar; yields (advance: call with each measured row, the Progress, its task)."""
    columns = (TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, transient=False) as progress:
        task = progress.add_task("measuring poses", total=total, completed=done)

        def advance(row: dict) -> None:
            progress.update(task, advance=1, description=f"{PHASES.get(row['phase'], row['phase'])} pose "
                            f"{row['index'] + 1}")

        yield advance, progress, task


@contextlib.contextmanager
def bar_aside(bar: Progress) -> Iterator[None]:
    """The bar off the terminal's screen while the operator reads and answers a question, then back below the answer.

    Its line is erased rather than left frozen above the question; without a terminal (output to a file or a pipe)
    nothing is drawn live and nothing changes.
    """
    live = bar.live
    if not live.is_started or not bar.console.is_terminal:
        yield
        return
    transient = live.transient
    live.transient = True  # stopping erases the bar's line
    live.stop()
    try:
        yield
    finally:
        live.transient = transient
        live.start(refresh=True)


def combine_observers(*observers: Observer | None) -> Observer | None:
    """One engine observer calling each given one in turn (a panel's pause, raised by the first, still wins)."""
    chosen = [o for o in observers if o is not None]
    if len(chosen) <= 1:
        return chosen[0] if chosen else None

    def observe(kind: str, data: dict) -> None:
        for o in chosen:
            o(kind, data)

    return observe


def adaptive_lines(bar: Progress, task: Any, after_measure: int) -> Observer:
    """An engine observer printing each adaptive decision above the bar and keeping the bar's total on forecast."""

    def observe(kind: str, data: dict) -> None:
        msg = data.get("message")
        if kind != "message" or not isinstance(msg, Checkpoint) or msg.label != PROGRESS_LABEL:
            return
        shown = msg.data or {}
        ahead = 0 if shown.get("stop") else ((shown.get("forecast") or {}).get("n_rows") or 0)
        bar.update(task, total=shown["n_rows"] + ahead + after_measure)
        bar.console.print(progress_line(shown), highlight=False, markup=False, soft_wrap=True)

    return observe
