"""What every `hilcal` command shares: the consoles, the bad-input exit, option types and the accuracy table.

Cheap to import (no numpy, no hilcal models): every command module imports it, and `hilcal --help` must start fast.
"""

from __future__ import annotations

import sys
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, NoReturn

import typer
from rich.console import Console
from rich.markup import escape

if TYPE_CHECKING:
    from rich.table import Table

    from hilcal.metrics import AccuracySummary
    from hilcal.robot import Robot

out = Console(width=None if sys.stdout.isatty() else 120, markup=False)
err = Console(stderr=True, markup=False)
"""Markup is off: messages carry paths, station sections and names, and rich would take `[timing]` for a style tag
and drop it. A message with markup passes ``markup=True`` and escapes what it prints (``rich.markup.escape``)."""

BAD_INPUT = 2


class EstimatorChoice(StrEnum):
    ls = "ls"
    linf = "linf"


class ModelChoice(StrEnum):
    m42 = "42"
    m60 = "60"


RobotOption = Annotated[Path | None, typer.Option("--robot", help="robot TOML file (default: paper Table 1)")]


def fail(message: str) -> NoReturn:
    """Print the message as an error and exit with code 2 (bad input)."""
    err.print(f"[bold red]error:[/] {escape(message)}", highlight=False, soft_wrap=True, markup=True)
    raise typer.Exit(BAD_INPUT)


def robot_or_fail(path: Path | None) -> Robot:
    """The robot file (None: the paper's Table 1 robot); exit 2 with the loader's message if it is bad."""
    from hilcal.robot import RobotFileError, load_robot

    try:
        return load_robot(path)
    except RobotFileError as e:
        fail(str(e))


def accuracy_table(title: str, columns: list[tuple[str, AccuracySummary | None]]) -> Table:
    """The paper's Table 7 layout: indicators as rows, (position, orientation) per condition as columns."""
    from rich.table import Table

    table = Table(title=title)
    table.add_column("indicator")
    for label, _ in columns:
        table.add_column(f"{label}\npos mm", justify="right")
        table.add_column(f"{label}\nori deg", justify="right")
    for indicator in ("max", "range", "mean", "rms"):
        cells = []
        for _, summary in columns:
            if summary is None:
                cells += ["n/a", "n/a"]
            else:
                cells += [f"{getattr(summary.position_mm, indicator):.4f}",
                          f"{getattr(summary.orientation_deg, indicator):.5f}"]
        table.add_row({"max": "maximum", "range": "range", "mean": "average", "rms": "RMS"}[indicator], *cells)
    return table


def write_simulated_recording(rb: Robot, out_path: Path, seed: int, errors: str, noise_mm: float) -> None:
    """32 D-optimal measurement poses and 24 verification poses on the in-process simulated rig, as a CSV."""
    import numpy as np

    from hilcal.planning import design as dsg
    from hilcal.recording import write_recording
    from procedures.cli.simulated_recording import simulate_recording
    from sim_devices.rig.config import RigConfig, load_errors

    try:
        config = RigConfig(seed=seed, errors=load_errors(errors, rb), cmm_noise_mm=noise_mm)
    except (ValueError, OSError) as e:
        fail(f"--errors {errors}: {e}")
    rng = np.random.default_rng(seed)
    measure = dsg.factorial_exchange(rb, 32, rng).poses
    verify = dsg.verification_poses(rb, 24, seed)
    write_recording(out_path, simulate_recording(rb, config, measure, verify))
