"""The `hilcal` command line: run, panel, sim, history, upload, rollback, identify, diagnose, identifiability,
design, simulate, demo.

Exit codes: 0 ok, 2 bad input (robot file, recording, options). Units: mm and degrees.
"""

from __future__ import annotations

import logging
import sys
from typing import Annotated

import structlog
import typer

from procedures.cli.analysis import design, diagnose, identifiability, identify, simulate
from procedures.cli.operator import history, rollback, run, upload
from procedures.cli.panel import panel
from procedures.cli.rig import demo, sim_command

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__)


@app.callback()
def main(verbose: Annotated[bool, typer.Option("--verbose", "-v", help="structured logs on stderr")] = False) -> None:
    """hilcal: kinematic calibration of 6-6 Gough/Stewart platforms (LS and L-infinity)."""
    structlog.configure(
        wrapper_class=structlog.make_filtering_bound_logger(logging.INFO if verbose else logging.WARNING),
        logger_factory=lambda *_: structlog.PrintLogger(sys.stderr),
    )


app.command()(identify)
app.command()(run)
app.command()(panel)
app.command("sim")(sim_command)
app.command()(history)
app.command()(upload)
app.command()(rollback)
app.command()(diagnose)
app.command()(identifiability)
app.command()(design)
app.command()(simulate)
app.command()(demo)

if __name__ == "__main__":
    app()
