"""The `hilcal` app: every command registered in one place, with the help a new user reads first (``HELP``).

Every command's help is laid out by ``procedures.cli.help_format`` (whole words at 80 columns). The commands import
their heavy libraries themselves, so `hilcal --help` starts fast.
"""

from __future__ import annotations

import logging
import sys
from typing import Annotated

import typer

from procedures.cli.analysis import design, diagnose, identifiability, identify, simulate
from procedures.cli.check import check
from procedures.cli.help_format import HelpCommand, HelpGroup
from procedures.cli.importing import import_command, robot_from_geometry_command
from procedures.cli.operator import rollback, run, upload
from procedures.cli.panel import panel
from procedures.cli.records import drift_command, history, records_app
from procedures.cli.rig import demo, sim_command
from procedures.cli.signoff import certificate

HELP = """hilcal calibrates Stewart platforms (6-6 Gough platforms: large hydraulic ones and small electric
hexapods): it measures the machine at chosen poses with a coordinate measuring machine or a laser tracker,
identifies the errors of its joints and legs, uploads the corrected geometry to the controller and verifies
the result. Every command also runs against simulated devices.

First steps: `hilcal run --sim --yes` calibrates a simulated machine; `hilcal robot-from-geometry
GEOMETRY.toml --out robot.toml` writes your machine's robot file from its datasheet, and `hilcal run --sim
--yes --robot robot.toml` calibrates it in simulation.

At the machine: run (measure, identify, upload, verify and sign off), check (every device of a station before
a shift), upload and rollback (a parameter set by hand), certificate (write a run's certificate again).
Planning and analysis: design, identify, diagnose, identifiability, simulate. Your machine's files:
robot-from-geometry, import. Records: history, drift, records. Simulation and demonstration: sim, demo, panel.

Lengths are in mm and angles in degrees. Exit codes: 0 done; 2 bad input (a file, a recording or an option;
the message names it); 3 a run stopped or a device did not answer; 4 a run complete but not accepted."""


class _Group(HelpGroup):
    """Typer's group that notes whether the sub-command is asked only for its help (then no logging set-up)."""

    def resolve_command(self, ctx: typer.Context, args: list[str]) -> tuple[str | None, object, list[str]]:
        name, command, rest = super().resolve_command(ctx, args)
        ctx.meta["hilcal.help_only"] = any(arg in ctx.help_option_names for arg in rest)
        return name, command, rest


app = typer.Typer(cls=_Group, add_completion=False, no_args_is_help=True, help=HELP)


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


app.command(cls=HelpCommand)(identify)
app.command(cls=HelpCommand)(run)
app.command(cls=HelpCommand)(check)
app.command(cls=HelpCommand)(panel)
app.command("sim", cls=HelpCommand)(sim_command)
app.command(cls=HelpCommand)(history)
app.command(cls=HelpCommand)(certificate)
app.command("drift", cls=HelpCommand)(drift_command)
app.add_typer(records_app, name="records")
app.command(cls=HelpCommand)(upload)
app.command(cls=HelpCommand)(rollback)
app.command(cls=HelpCommand)(diagnose)
app.command(cls=HelpCommand)(identifiability)
app.command(cls=HelpCommand)(design)
app.command(cls=HelpCommand)(simulate)
app.command("import", cls=HelpCommand)(import_command)
app.command("robot-from-geometry", cls=HelpCommand)(robot_from_geometry_command)
app.command(cls=HelpCommand)(demo)

if __name__ == "__main__":
    app()
