"""The operator panel on the command line: `hilcal run --panel` (the run in a browser) and `hilcal panel` (history)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

import typer

from procedures.cli.common import fail, out

DEFAULT_PORT = 8765
PortOption = Annotated[int, typer.Option("--port", help="panel port (0: any free port)", min=0, max=65535)]


def say(text: str) -> None:
    """Plain text to the terminal (no rich markup: operator questions may hold brackets)."""
    out.print(text, markup=False, highlight=False, soft_wrap=True)


def run_with_panel(execute: Callable[[Any], Any], *, host: str, port: int, operator: str | None, yes: bool,
                   records: str | Path, linger_min: float) -> Any:
    """Serve the panel around `execute(session)` (the run); keep it up afterwards unless unattended."""
    from procedures.panel.server import PanelStartError
    from procedures.panel.session import PanelSession

    try:
        session = PanelSession(host=host, port=port, operator=operator, yes=yes, records_path=records, say=say)
        say(f"operator panel: {session.start()}")
    except PanelStartError as e:
        fail(str(e))
    try:
        result = execute(session)
        if not yes:
            session.linger(60.0 * linger_min, say=say)
        return result
    finally:
        session.close()


def panel(
    records: Annotated[str | None, typer.Option(help="records database: a SQLite file path or a URL "
                                                "(postgresql+psycopg://user@host/db); default: $HILCAL_RECORDS, else "
                                                "~/.local/share/hilcal/records.sqlite")] = None,
    port: PortOption = DEFAULT_PORT,
    host: Annotated[str, typer.Option(help="address; other than the loopback needs the printed token")] = (
        "127.0.0.1"),
) -> None:
    """The operator panel without a run: past runs, their reports and uploads, in a browser (until Ctrl-C)."""
    from procedures.panel.server import PanelStartError
    from procedures.panel.session import serve_history
    from procedures.runner import default_records_path

    try:
        serve_history(records or default_records_path(), host, port, say=say)
    except PanelStartError as e:
        fail(str(e))
