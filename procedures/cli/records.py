"""Commands on the calibration records: `hilcal history` (runs and uploads, of one machine or all),
`hilcal drift` (how a machine's geometry moved between calibrations) and `hilcal records sync` (write the records
that runs kept in their journals while the database was away).

Exit codes: 0 ok, 2 bad input (a bad URL, an unknown machine), 3 the database does not answer.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer
from rich.markup import escape

from procedures.cli.common import err, fail, out
from procedures.cli.help_format import HelpCommand, HelpGroup

UNAVAILABLE = 3
RecordsOption = Annotated[str | None, typer.Option(
    "--records", help="records database: a SQLite file path or a URL (postgresql+psycopg://user@host/db); "
                      "default: $HILCAL_RECORDS, else ~/.local/share/hilcal/records.sqlite")]

records_app = typer.Typer(cls=HelpGroup, no_args_is_help=True,
                          help="The calibration records: sync (write what runs kept while the database was away), "
                          "machines (every machine recorded).")


def unavailable(message: str) -> NoReturn:
    err.print(f"[bold red]records unavailable:[/] {escape(message)}", highlight=False, markup=True)
    raise typer.Exit(UNAVAILABLE)


def open_records(target: str | Path | None) -> Any:
    """The records (exit 2 for a bad target, 3 if the database does not answer)."""
    from procedures.records import Records, RecordsError, RecordsUnavailable

    try:
        return Records(target)
    except RecordsError as e:
        fail(f"records: {e}")
    except RecordsUnavailable as e:
        unavailable(str(e))


def _known_machine(db: Any, machine: str) -> None:
    known = [m["machine"] for m in db.machines()]
    if machine not in known:
        fail(f"no machine {machine!r} in the records {db.where}; known: {', '.join(known) or 'none'}")


def history(
    limit: Annotated[int, typer.Option(min=1, help="newest entries to show")] = 20,
    records: RecordsOption = None,
    machine: Annotated[str | None, typer.Option(help="only this machine (robot name/serial, see `records "
                                                     "machines`)")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="one JSON object instead of the table")] = False,
) -> None:
    """Past runs, parameter sets and uploads from the calibration records, newest first."""
    from procedures.records import RecordsUnavailable, format_history

    db = open_records(records)
    try:
        with db:
            if machine is not None:
                _known_machine(db, machine)
            rows = db.history(limit, machine=machine)
    except RecordsUnavailable as e:
        unavailable(str(e))
    if as_json:
        out.print_json(json.dumps({"records": db.where, "machine": machine, "entries": rows}))
    else:
        out.print(format_history(rows), highlight=False, markup=False, soft_wrap=True)


def drift_command(
    machine: Annotated[str, typer.Option(help="the machine (robot name/serial, see `hilcal records machines`)")],
    records: RecordsOption = None,
    threshold_mm: Annotated[float, typer.Option(min=0.0, help="smallest change that counts (mm)")] = 0.05,
    plot: Annotated[Path | None, typer.Option(help="write trend plots (PNG) of the flagged parameters and the "
                                                   "legs' strokes at home")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="one JSON object instead of the text")] = False,
) -> None:
    """How the machine's identified geometry moved across its calibrations: flags beyond 3σ and the threshold."""
    from hilcal.drift import describe, drift
    from procedures.records import RecordsUnavailable

    db = open_records(records)
    try:
        with db:
            _known_machine(db, machine)
            calibrations = db.calibrations(machine)
    except RecordsUnavailable as e:
        unavailable(str(e))
    result = drift(calibrations, machine, threshold_mm=threshold_mm).to_json()
    if plot is not None:
        _write_plot(result, plot)
    if as_json:
        out.print_json(json.dumps(result))
        return
    say = out.print
    say(f"machine {machine}: {result['n_calibrations']} calibrations with parameters in {db.where}",
        highlight=False, markup=False)
    say(f"rule: {result['rule']}", highlight=False, markup=False, soft_wrap=True)
    if result["n_calibrations"] < 2:
        say("fewer than two calibrations: nothing to compare", highlight=False)
        return
    flags = result["flags"]
    say("flags:" if flags else "no parameter moved beyond the rule", highlight=False)
    for sentence in flags:
        say(f"  {sentence}", highlight=False, markup=False, soft_wrap=True)
    since = result["since_last"]
    if since:
        say("since the previous calibration:", highlight=False)
        for sentence in since:
            say(f"  {sentence}", highlight=False, markup=False, soft_wrap=True)
    say(f"{'parameter':<28} {'since last mm':>14} {'σ':>6} {'best step mm':>13} {'σ':>6} {'mm/month':>9}",
        highlight=False, markup=False)
    for p in result["parameters"]:
        if p["name"].endswith(("_stroke_at_home_mm", "_l0_mm")) or p["flag"]:
            say(f"{describe(p['name'])[0]:<28} {_f(p['since_last_mm'], 4):>14} {_f(p['since_last_sigma'], 1):>6} "
                f"{_f(p['step_mm'], 4):>13} {_f(p['step_sigma'], 1):>6} {_f(p['slope_mm_per_month'], 4):>9}",
                highlight=False, markup=False)


def _f(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:+.{digits}f}"


def _write_plot(result: dict[str, Any], path: Path) -> None:
    import base64

    from hilcal.reports.drift import trend_png

    png = trend_png(result)
    if png is None:
        fail("nothing to plot: the machine has fewer than two calibrations with parameters")
    path.write_bytes(base64.b64decode(png))
    out.print(f"trend plots: {path}", highlight=False)


@records_app.command("sync", cls=HelpCommand)
def sync(
    folders: Annotated[list[Path], typer.Argument(help="run folders, or folders holding run folders")],
    records: RecordsOption = None,
) -> None:
    """Write the records that runs kept in their journals (the database was away); idempotent."""
    from procedures.records import RecordsUnavailable
    from procedures.records.sync import sync_folders

    missing = [str(f) for f in folders if not f.exists()]
    if missing:
        fail(f"no such folder: {', '.join(missing)}")
    db = open_records(records)
    try:
        with db:
            report = sync_folders(db, folders, say=lambda text: out.print(text, highlight=False, markup=False))
    except RecordsUnavailable as e:
        unavailable(f"{e}; nothing more was written, the journals keep the rest")
    out.print(f"{len(report.written)} run(s) written to {db.where}; {len(report.nothing_staged)} journal(s) had "
              f"nothing staged; {len(report.failed)} failed", highlight=False, markup=False)
    if report.failed:
        raise typer.Exit(1)


@records_app.command("machines", cls=HelpCommand)
def machines(records: RecordsOption = None) -> None:
    """Every machine in the records: its identity, number of runs and the newest run."""
    from procedures.records import RecordsUnavailable

    db = open_records(records)
    try:
        with db:
            rows = db.machines()
    except RecordsUnavailable as e:
        unavailable(str(e))
    if not rows:
        out.print("no machines recorded", highlight=False)
    for row in rows:
        out.print(f"{row['machine']:<40} {row['runs']:>6} runs, newest {row['last_run']}", highlight=False,
                  markup=False)
