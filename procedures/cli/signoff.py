"""The sign-off on the command line: `hilcal certificate RUN_DIR` (the certificate again from a run folder), the
acceptance test's choice for `hilcal run` and `hilcal design`, and asking for the operator's name.

Exit codes of a run's sign-off: 0 accepted (or no limits set), 4 complete but not accepted (verdict fail or not
proven), see docs/certificate.md.
"""

from __future__ import annotations

import json
import sys
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from procedures.cli.common import err, fail, out

if TYPE_CHECKING:
    from hilcal.robot import Robot
    from procedures.timing import TimingSection

NOT_ACCEPTED = 4
"""A complete run whose sign-off verdict is fail or not proven (``procedures.runner.EXIT_NOT_ACCEPTED``)."""


class AcceptanceChoice(StrEnum):
    iso9283 = "iso9283"


AcceptanceOption = Annotated[AcceptanceChoice | None, typer.Option(
    help="acceptance test after the verification: iso9283 (ISO 9283 pose accuracy and repeatability, P1-P5)")]
CyclesOption = Annotated[int, typer.Option(help="cycles of the acceptance test (ISO 9283: 30)", min=2, max=1000)]


def ask_operator() -> str | None:
    """The operator's name for the run and its certificate, asked at an interactive terminal (empty, or no
    terminal: none, and the station file's operator counts)."""
    if not sys.stdin.isatty():
        return None
    name = typer.prompt("Operator's name (recorded with the run and on the certificate)", default="",
                        show_default=False).strip()
    return name or None


def print_acceptance_design(robot: Robot, seed: int, timing: TimingSection, cycles: int) -> None:
    """`hilcal design --acceptance iso9283`: the test cube, P1-P5 and the test's estimated machine time."""
    from rich.table import Table

    from hilcal.acceptance.iso9283 import CYCLE_ORDER, POSE_NAMES
    from hilcal.planning.machine_time import format_minutes
    from procedures.acceptance import make_acceptance
    from procedures.plan import PlanError, estimate_plan, make_plan

    try:
        plan = make_plan(robot, seed, timing=timing.timing())
        test = make_acceptance(robot, plan, cycles)
    except PlanError as e:
        fail(str(e))
    table = Table(title=test.describe(), title_justify="left")
    for column in ("pose", "x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"):
        table.add_column(column, justify="left" if column == "pose" else "right")
    for name, pose in zip(POSE_NAMES, test.poses, strict=True):
        table.add_row(name, *(f"{v:.3f}" for v in pose))
    out.print(table)
    route, _ = test.route()
    phase = estimate_plan(plan, robot, timing.timing(), acceptance_poses=route).phase("acceptance")
    out.print(f"P1 is the centre of the test cube; P2-P5 lie on its diagonal plane C1-C2-C7-C8 (y = z), 10 % of the "
              f"diagonal from C1, C2, C7, C8. Each cycle visits {', '.join(POSE_NAMES[k] for k in CYCLE_ORDER)}. "
              f"Estimated machine time of the test after the calibration plan (seed {seed}): "
              f"{format_minutes(phase.total_s)} for {phase.n_poses} measurements ({timing.describe()}).",
              highlight=False, soft_wrap=True)


def certificate(
    run_dir: Annotated[Path, typer.Argument(help="run folder of a complete run (with report.json)")],
) -> None:
    """Write certificate.html and certificate.pdf of a run again from its report.json; exit 4 if not accepted."""
    from procedures.certificate import regenerate_certificate, verdict_line

    try:
        html_path, pdf_path, problem = regenerate_certificate(run_dir)
    except ValueError as e:
        fail(str(e))
    report = json.loads((run_dir / "report.json").read_text())
    out.print(verdict_line(report), highlight=False, markup=False, soft_wrap=True)
    out.print(f"certificate {report['certificate']['number']}: {html_path}" +
              (f" and {pdf_path}" if pdf_path else ""), highlight=False, markup=False, soft_wrap=True)
    if problem:
        err.print(f"warning: {problem}", highlight=False, markup=False, soft_wrap=True)
    if report["certificate"]["verdict"] in ("fail", "not proven"):
        raise typer.Exit(NOT_ACCEPTED)
