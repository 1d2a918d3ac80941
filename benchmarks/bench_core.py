"""Timing benchmark of hilcal's core: identification (LS and L∞ variants), batched forward kinematics vs a
per-pose scipy fsolve loop, and (when present) pose design via ``benchmarks/bench_design.run()``.

Why: the calibration runs interactively on the shop floor, so its cost per fit and the payoff of the batched
Newton solver should be known and tracked. Prints a Markdown table and writes docs/benchmarks.md.
Run ``python benchmarks/bench_core.py [--quick]``.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import scipy
import structlog
from scipy.optimize import fsolve

from hilcal.identification import IdentificationResult, identify
from hilcal.kinematics import Geometry, forward_kinematics, inverse_kinematics
from hilcal.planning.design import factorial_exchange, random_poses, verification_poses
from hilcal.robot import Robot, default_robot, rotation_matrix
from procedures.cli.simulated_recording import simulate_recording
from sim_devices.rig.config import RigConfig, load_errors

ROOT = Path(__file__).resolve().parents[1]
DOC_PATH = ROOT / "docs" / "benchmarks.md"
N_FK_POSES = 1000
NOISE_MM = 0.005

IDENTIFICATION_CASES: tuple[tuple[str, str, str, str], ...] = (
    ("ls", "42", "forward", "iterated"),
    ("ls", "42", "forward", "one_step"),
    ("ls", "42", "implicit", "iterated"),
    ("ls", "42", "implicit", "one_step"),
    ("linf", "42", "forward", "iterated"),
    ("linf", "42", "forward", "one_step"),
    ("linf", "42", "implicit", "iterated"),
    ("linf", "42", "implicit", "one_step"),
    ("ls", "60", "forward", "one_step"),
    ("linf", "60", "forward", "one_step"),
)


def timed(fn: Callable[[], object], repeats: int) -> tuple[float, object]:
    """Median wall time (s) of `repeats` calls (time.perf_counter) and the last call's value."""
    times, value = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        value = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), value


def md_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def bench_identification(robot: Robot, repeats: int) -> str:
    """Identification of 32 poses (pose set 3, Table 2 errors, σ = 0.005 mm) for every estimator variant."""
    errors = load_errors("table2", robot)
    poses = factorial_exchange(robot, 32, np.random.default_rng(0)).poses
    rec = simulate_recording(
        robot, RigConfig(seed=0, errors=errors, cmm_noise_mm=NOISE_MM), poses, verification_poses(robot, 4, 0)
    ).select("measure")
    rows = []
    for est, model, form, method in IDENTIFICATION_CASES:
        t, res = timed(
            lambda est=est, model=model, form=form, method=method: identify(
                robot, rec.legs_mm, rec.meas, estimator=est, model=model, formulation=form, method=method
            ),
            repeats,
        )
        assert isinstance(res, IdentificationResult)
        rows.append([
            {"ls": "LS", "linf": "L∞"}[est], model, form, method, f"{1000 * t:.1f}", str(res.n_iterations),
            "yes" if res.converged else "no", f"{res.max_abs_residual:.4f}",
        ])
    header = ["estimator", "model", "formulation", "method", "median time (ms)", "iterations / evals",
              "converged", "max residual (mm)"]
    return (f"### Identification, {len(rec.legs_mm)} poses (median of {repeats})\n\n"
            "Pose set 3 (factorial + exchange), Table 2 errors, CMM noise σ = "
            f"{NOISE_MM} mm, simulated rig. *iterations / evals*: LM function evaluations for LS, LPs for L∞.\n\n"
            + md_table(header, rows))


def fsolve_fk(geom: Geometry, lengths: np.ndarray, home: np.ndarray) -> np.ndarray:
    """Per-pose FK with scipy.optimize.fsolve on the 6 leg-length equations, from the home pose (mm, deg)."""
    x0 = home.astype(float).copy()
    x0[3:] = np.radians(x0[3:])
    out = np.empty_like(lengths)
    for k, target in enumerate(lengths + geom.dl0):

        def equations(x: np.ndarray, target: np.ndarray = target) -> np.ndarray:
            R = rotation_matrix(x[3:])
            return np.linalg.norm(geom.a @ R.T + x[:3] - geom.b, axis=1) - target

        x, _info, ier, msg = fsolve(equations, x0, full_output=True, xtol=1e-12)
        if ier != 1:
            raise RuntimeError(f"fsolve failed on pose {k}: {msg}")
        out[k] = np.concatenate([x[:3], np.degrees(x[3:])])
    return out


def bench_fk(robot: Robot, repeats: int) -> str:
    """Batched Newton FK vs a per-pose fsolve loop on the same N poses of the Table 2 geometry."""
    geom = Geometry.nominal(robot).perturbed(load_errors("table2", robot).to_vector())
    poses = random_poses(robot, N_FK_POSES, np.random.default_rng(1))
    lengths = inverse_kinematics(geom, poses)
    t_batch, q_batch = timed(lambda: forward_kinematics(geom, lengths, robot.home), repeats)
    t_loop, q_loop = timed(lambda: fsolve_fk(geom, lengths, robot.home), max(1, repeats // 2))
    q_batch, q_loop = np.asarray(q_batch), np.asarray(q_loop)
    agree = np.max(np.abs(q_batch - q_loop))
    truth = np.max(np.abs(q_batch - poses))
    rows = [
        ["batched Newton (`forward_kinematics`)", f"{1000 * t_batch:.1f}", f"{1e6 * t_batch / N_FK_POSES:.1f}", "1"],
        ["per-pose `scipy.optimize.fsolve` loop", f"{1000 * t_loop:.1f}", f"{1e6 * t_loop / N_FK_POSES:.1f}",
         f"{t_loop / t_batch:.0f}"],
    ]
    return (f"### Forward kinematics, N = {N_FK_POSES} poses (median of {repeats} / {max(1, repeats // 2)})\n\n"
            "Random feasible poses, Table 2 geometry, both solvers start from the home pose.\n\n"
            + md_table(["solver", "time (ms)", "per pose (µs)", "slowdown vs batched"], rows)
            + f"\n\nSpeed-up of the batched solver: **{t_loop / t_batch:.0f} ×**. Largest difference between the two "
            f"solutions: {agree:.2g} (mm / deg); batched vs the poses that generated the lengths: {truth:.2g}.")


def bench_design_section() -> str:
    """Call benchmarks.bench_design.run() if that module exists and render what it returns."""
    sys.path.insert(0, str(ROOT))
    try:
        module = importlib.import_module("benchmarks.bench_design")
    except ModuleNotFoundError:
        return "### Pose design\n\n`benchmarks/bench_design.py` is not present: skipped."
    t0 = time.perf_counter()
    result = module.run()
    elapsed = time.perf_counter() - t0
    head = f"### Pose design (`benchmarks.bench_design.run()`, {elapsed:.1f} s in total)\n\n"
    if isinstance(result, Mapping) and all(isinstance(v, Mapping) for v in result.values()):
        keys = list(dict.fromkeys(k for v in result.values() for k in v))
        rows = [[str(name), *(_cell(entry.get(k)) for k in keys)] for name, entry in result.items()]
        return head + md_table(["design", *keys], rows)
    return head + f"```\n{result}\n```"


def _cell(value: object) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return "" if value is None else str(value)


def _included(name: str, title: str) -> str:
    """The figures of another generated page (its header line names the command and the date), or ''."""
    path = DOC_PATH.parent / name
    if not path.exists():
        return ""
    _, generated, body = path.read_text().split("\n\n", 2)
    return f"### {title} (from [{name}]({name}))\n\n{generated}\n\n{body.strip()}"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats")
    args = parser.parse_args(argv)
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    repeats = 2 if args.quick else 5
    robot = default_robot()
    t0 = time.perf_counter()
    sections = [bench_identification(robot, repeats), bench_fk(robot, repeats), bench_design_section()]
    elapsed = time.perf_counter() - t0
    command = "python benchmarks/bench_core.py" + (" --quick" if args.quick else "")
    now = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    head = (
        "# Core benchmarks\n\n"
        f"Generated by `{command}` on {now} in {elapsed:.0f} s.\n"
        f"Machine: {platform.platform()}, {platform.machine()}, os.cpu_count() = {os.cpu_count()}; "
        f"Python {platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__}. "
        "Times are wall-clock medians (`time.perf_counter`).\n"
    )
    sections += [_included("benchmarks_startup.md", "Command-line start-up"),
                 _included("benchmarks_tests.md", "Test suite")]
    text = "\n\n".join([head, *[x for x in sections if x]]) + "\n"
    print(text)
    DOC_PATH.parent.mkdir(parents=True, exist_ok=True)
    DOC_PATH.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
