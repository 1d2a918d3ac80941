"""The `hilcal` command line: run, panel, sim, history, upload, rollback, identify, diagnose, identifiability,
design, simulate, import, robot-from-geometry, demo.

Heavy libraries (numpy, scipy, matplotlib, the panel's server, the records' database, the device protocols) are
imported inside the commands that use them: `hilcal --help` imports none of them (tests/cli/test_startup.py).

Exit codes: 0 ok, 2 bad input (robot file, recording, options), 3 a run stopped (resumable),
4 a run complete but not accepted (its sign-off verdict). Units: mm and degrees.
"""

from __future__ import annotations

import logging
import sys
from typing import Annotated

import typer
from typer.core import TyperGroup

from procedures.cli.analysis import design, diagnose, identifiability, identify, simulate
from procedures.cli.check import check
from procedures.cli.importing import import_command, robot_from_geometry_command
from procedures.cli.operator import rollback, run, upload
from procedures.cli.panel import panel
from procedures.cli.records import drift_command, history, records_app
from procedures.cli.rig import demo, sim_command
from procedures.cli.signoff import certificate


class _Group(TyperGroup):
    """Typer's group that notes whether the sub-command is asked only for its help (then no logging set-up)."""

    def resolve_command(self, ctx: typer.Context, args: list[str]) -> tuple[str | None, object, list[str]]:
        name, command, rest = super().resolve_command(ctx, args)
        ctx.meta["hilcal.help_only"] = any(arg in ctx.help_option_names for arg in rest)
        return name, command, rest


app = typer.Typer(cls=_Group, add_completion=False, no_args_is_help=True, help=__doc__)


@app.callback()
def main(ctx: typer.Context,
         verbose: Annotated[bool, typer.Option("--verbose", "-v", help="structured logs on stderr")] = False) -> None:
    """hilcal: kinematic calibration of 6-6 Gough/Stewart platforms (LS and L-infinity)."""
    if ctx.meta.get("hilcal.help_only"):
        return  # `hilcal CMD --help` prints and exits: structlog's import (~40 ms) would only slow it down
    import structlog

    structlog.configure(
        wrapper_class=structlog.make_filtering_bound_logger(logging.INFO if verbose else logging.WARNING),
        logger_factory=lambda *_: structlog.PrintLogger(sys.stderr),
    )


app.command()(identify)
app.command()(run)
app.command()(check)
app.command()(panel)
app.command("sim")(sim_command)
app.command()(history)
app.command()(certificate)
app.command("drift")(drift_command)
app.add_typer(records_app, name="records")
app.command()(upload)
app.command()(rollback)
app.command()(diagnose)
app.command()(identifiability)
app.command()(design)
app.command()(simulate)
app.command("import")(import_command)
app.command("robot-from-geometry")(robot_from_geometry_command)
app.command()(demo)

if __name__ == "__main__":
    app()
