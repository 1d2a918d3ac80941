"""Machine time of a calibration: design order against the optimised order, time-budgeted designs, and whole
simulated runs with each order. Writes docs/benchmarks_machine_time.md.

Why: on a hydraulic platform the moves between poses take tens of minutes of every calibration; the
ordering must halve motion time quickly (< 1 s) without confounding drift with the workspace, and a time
budget must say what it costs in accuracy. ``python benchmarks/bench_machine_time.py [--quick]``.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import structlog
from _docs import write_doc
from scipy.spatial.transform import Rotation

from drivers.cmm.probing import REGISTERED_DEG, REGISTERED_MM
from hilcal.identification import identify
from hilcal.kinematics import Geometry, forward_kinematics, inverse_kinematics
from hilcal.metrics import pose_errors
from hilcal.planning.budget import BudgetError, budgeted_design
from hilcal.planning.machine_time import MotionRules, MotionTiming, calibration_phases, estimate_route
from hilcal.planning.ordering import drift_confounding, order_route
from hilcal.robot import Robot, default_robot, load_robot
from procedures.journal import Journal
from procedures.plan import (
    distinct_measure_poses,
    make_plan,
    motion_rules,
    order_plan_route,
    plan_from_poses,
    save_plan,
)
from procedures.station import Devices, open_devices, station_from_channels
from procedures.timing import TimingSection
from sim_devices.sim_config import load_sim_config
from sim_devices.simulator import start_sim

ROOT = Path(__file__).resolve().parent.parent
SMALL_ROBOT = ROOT / "examples" / "hexapod_small.toml"
NOISE_MM = 0.005
SMALL_TIMING = MotionTiming(leg_speed_mm_s=20.0, leg_accel_mm_s2=200.0, settle_s=0.2, cmm_s_per_pose=20.0,
                            move_overhead_s=0.1)
"""A small electric hexapod: 20 mm/s, 200 mm/s², 0.2 s settle, 20 s of probing, 0.1 s per move."""


SLOW_SIM = """
[controller]
time_scale = 10.0
"""
"""The simulated runs: the servo at a tenth of the default speed-up, so that motion is a visible part of a run."""
MAX_RESUMES = 5
"""A run whose controller link drops on a busy machine (a late heartbeat) is resumed, as an operator would."""
PRIORITY = ["nice", "-n", "-10"] if hasattr(os, "geteuid") and os.geteuid() == 0 else []
"""Runs (and the simulator they spawn) at a higher priority when allowed, so that other load on a shared machine
does not delay the 20 ms heartbeats past the 0.1 s timeout."""


def robots() -> list[tuple[str, Robot, MotionTiming]]:
    station = TimingSection().timing()
    return [("paper Table 1 (hydraulic, 4.3 m legs)", default_robot(), station),
            ("small electric hexapod (examples/hexapod_small.toml)", load_robot(SMALL_ROBOT), SMALL_TIMING)]


def ordering_rows(name: str, robot: Robot, timing: MotionTiming, repeats: int) -> list[str]:
    """Design order, the plan's least-time order (median solver time of `repeats` runs, wall and CPU) and the
    least-time order without the drift bound."""
    geom = Geometry.nominal(robot)
    design = make_plan(robot, 0, order="design", timing=timing)
    rules = motion_rules(design)
    unique, counts = distinct_measure_poses(design)
    verify = design.poses("verify")
    out = []

    def line(label: str, order_m: np.ndarray, order_v: np.ndarray, solver: str, base_s: float | None) -> float:
        m_rows = np.repeat(unique[order_m], counts[order_m], axis=0)
        est = estimate_route(geom, robot.home, calibration_phases(m_rows, verify[order_v]), rules, timing, robot.home)
        first = np.concatenate([[0], np.cumsum(counts[order_m])[:-1]])
        times = _visit_times(geom, robot, m_rows, rules, timing)[first]
        conf = drift_confounding(geom, unique[order_m], times, counts[order_m])
        ratio = "1" if base_s is None else f"{est.motion_s / base_s:.3f}"
        out.append(f"| {name} | {label} | {est.leg_travel_mm / 1000:.1f} | {est.motion_s / 60:.1f} | {ratio} | "
                   f"{est.total_s / 60:.1f} | {solver} | {conf.absorbed_fraction:.2f} | {conf.max_abs_corr_pose:.2f} |")
        return est.motion_s

    base = line("design order", np.arange(len(unique)), np.arange(len(verify)), "-", None)
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        route = order_plan_route(robot, unique, verify, design, timing, counts)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    line(f"least-time (drift bound {route.confounding_bound:.2f})", route.measure_order, route.verify_order,
         f"{statistics.median(wall):.2f} ({statistics.median(cpu):.2f} CPU)", base)
    free = order_route(geom, robot.home, unique, verify, rules, timing, measure_counts=counts, seed=design.seed,
                       confounding_bound=1.0, leg_limits=robot.leg_limits)
    line("least-time, drift bound off", free.measure_order, free.verify_order, f"{free.solver_s:.2f}", base)
    return out


def _visit_times(geom: Geometry, robot: Robot, rows: np.ndarray, rules: MotionRules, timing: MotionTiming
                 ) -> np.ndarray:
    """Estimated time of each measure row (s from the start at home)."""
    t, out, pose = 0.0, [], robot.home
    for q in rows:
        t += estimate_route(geom, pose, [("x", q[None])], rules, timing).total_s
        out.append(t)
        pose = q
    return np.array(out)


def empirical_verify_rms(robot: Robot, rows: np.ndarray, verify: np.ndarray, reps: int, seed: int) -> float:
    """RMS position error at the verify poses of `reps` LS identifications from noisy measure rows."""
    rng = np.random.default_rng(seed)
    true = Geometry.nominal(robot).perturbed(rng.normal(0.0, 0.5, 42))
    legs, legs_v = inverse_kinematics(true, rows), inverse_kinematics(true, verify)
    length = robot.characteristic_length_mm
    errors = []
    for _ in range(reps):
        noisy = rows.copy()
        noisy[:, :3] += rng.normal(0.0, NOISE_MM, (len(rows), 3))
        turn = Rotation.from_rotvec(rng.normal(0.0, NOISE_MM / length, (len(rows), 3)))
        noisy[:, [5, 4, 3]] = (turn * Rotation.from_euler("ZYX", rows[:, [5, 4, 3]], degrees=True)).as_euler(
            "ZYX", degrees=True)
        fit = identify(robot, legs, noisy)
        errors.append(pose_errors(forward_kinematics(fit.geometry(robot), legs_v, verify), verify)[0])
    return float(np.sqrt(np.mean(np.square(errors))))


def budget_rows(name: str, robot: Robot, timing: MotionTiming, fractions: Sequence[float], reps: int) -> list[str]:
    """Budgets as fractions of the full plan's optimised time: chosen size, time, D-efficiency, predicted error."""
    plan = make_plan(robot, 0, order="design", timing=timing)
    rules = motion_rules(plan)
    unique, counts = distinct_measure_poses(plan)
    verify = plan.poses("verify")
    repeat = int(np.flatnonzero(counts > 1)[0]) if np.any(counts > 1) else None
    extra = int(counts.max() - 1)
    out = []
    full_s = None
    for fraction in fractions:
        budget = np.inf if full_s is None else fraction * full_s
        t0 = time.perf_counter()
        try:
            result = budgeted_design(robot, unique, verify, budget, rules, timing, repeat=repeat, repeats=extra,
                                     noise_mm=NOISE_MM)
        except BudgetError as e:
            out.append(f"| {name} | {fraction:.0%} ({budget / 60:.1f} min) | does not fit: {e} | | | | | | |")
            continue
        solve = time.perf_counter() - t0
        c = result.chosen
        full_s = full_s or c.estimate.total_s
        idx = c.measure_index[c.route.measure_order]
        rows = np.repeat(unique[idx], counts[idx], axis=0)
        empirical = empirical_verify_rms(robot, rows, verify, reps, seed=1)
        label = "none (full plan)" if not np.isfinite(budget) else f"{fraction:.0%} ({budget / 60:.1f} min)"
        out.append(f"| {name} | {label} | {c.n_measure} | {c.estimate.total_s / 60:.1f} | {c.d_efficiency:.3f} | "
                   f"{1000 * c.predicted.rms_position_mm:.2f} | {1000 * empirical:.2f} | "
                   f"{1000 * c.predicted.max_position_mm:.2f} | {solve:.1f} |")
    return out


def characterise(sim_toml: str | None, work: Path) -> tuple[TimingSection, str]:
    """Time the simulated station through the real drivers, as one would a real machine: leg moves of 1 and
    100 mm (overhead and speed), and pose measurements. Returns the [timing] section and a table row."""
    path = None
    if sim_toml is not None:
        path = work / "characterise.toml"
        path.write_text(sim_toml)
    with start_sim(load_sim_config(path)) as sim:
        station = station_from_channels(sim.channels())
        patient = station.motion.model_copy(update={"heartbeat_timeout_s": 0.5})  # a busy benchmark machine
        with open_devices(station.model_copy(update={"motion": patient})) as dev:
            return _time_devices(dev, sim_toml)


def _time_devices(dev: Devices, sim_toml: str | None) -> tuple[TimingSection, str]:
    """The timed moves and pose measurements of ``characterise`` on open devices."""
    dev.controller.enable()
    legs = np.asarray(dev.controller.feedback().lengths_mm, dtype=float)

    def move(d_mm: float) -> float:
        t0 = time.perf_counter()
        dev.controller.move_legs(legs - d_mm, 60.0)
        elapsed = time.perf_counter() - t0
        dev.controller.move_legs(legs, 60.0)
        return elapsed

    short = statistics.median(move(1.0) for _ in range(10))
    long = statistics.median(move(100.0) for _ in range(5))
    dev.cmm.start_session()
    dev.cmm.home()
    alignment = dev.cmm.measure_pose(dev.robot, dev.cmm_alignment).refined_alignment  # the run's first pose
    t0 = time.perf_counter()
    for _ in range(3):  # every later pose, as the run measures it: on the alignment the pose before registered
        alignment = dev.cmm.measure_pose(dev.robot, alignment, alignment_tolerance=(REGISTERED_MM, REGISTERED_DEG),
                                         registered=True).refined_alignment
    cmm_s = (time.perf_counter() - t0) / 3
    dev.controller.disable()
    speed = 99.0 / max(long - short, 1e-6)
    timing = TimingSection(leg_speed_mm_s=round(speed, -1), leg_accel_mm_s2=1e6, settle_s=0.05,
                           cmm_s_per_pose=round(cmm_s, 3), move_overhead_s=round(max(short - 1.0 / speed, 0.0), 3))
    label = "default simulator" if sim_toml is None else "simulator, servo time_scale 10"
    row = (f"| {label} | {1000 * short:.0f} | {1000 * long:.0f} | {speed:.0f} | {1000 * cmm_s:.0f} | "
           f"`{timing.describe()}` |")
    return timing, row


def simulated_runs(work: Path, timing: TimingSection) -> list[str]:
    """`hilcal run --sim` on the slowed simulator with the design-order and the least-time plan, same seeds."""
    robot = default_robot()
    design = make_plan(robot, 0, timing=timing.timing(), order="design")
    timed = plan_from_poses(robot, distinct_measure_poses(design)[0], design.poses("verify"),
                            timing=timing.timing(), seed=0, settle_s=design.settle_s)
    (work / "sim.toml").write_text(SLOW_SIM)
    lines = "".join(f"{k} = {v!r}\n" for k, v in timing.model_dump().items())
    (work / "station.toml").write_text("[timing]\n" + lines)
    out = []
    for label, plan in (("design order", design), ("least-time order", timed)):
        save_plan(plan, work / f"{plan.order}.json")
        env = {**os.environ, "HILCAL_RECORDS": str(work / "records.sqlite")}
        run_dir = work / f"run-{plan.order}"
        args = ["--sim-config", str(work / "sim.toml"), "--station", str(work / "station.toml"), "--station-timing",
                "--plan", str(work / f"{plan.order}.json")]
        t0 = time.perf_counter()
        resumes = 0
        while True:
            done = subprocess.run([*PRIORITY, sys.executable, "-m", "procedures.cli", "run", "--sim", "--yes",
                                   "--out", str(run_dir), *args], env=env, capture_output=True, text=True, check=False)
            if done.returncode != 3 or resumes >= MAX_RESUMES:
                break
            resumes += 1
            with Journal(run_dir / "journal.sqlite") as journal:
                args = ["--resume", journal.run_info()["run_id"]]
        wall = time.perf_counter() - t0
        if done.returncode != 0:
            raise RuntimeError(f"hilcal run failed: {done.stdout[-1500:]} {done.stderr[-1500:]}")
        report = json.loads((run_dir / "report.json").read_text())
        mt, after = report["machine_time"], report["verification"]["after"]
        phases = " / ".join(f"{p['estimated_s']:.0f} → {p['actual_s']:.0f}" for p in mt["phases"].values()
                            if p["actual_s"] is not None)
        travel_m = sum(p["leg_travel_mm"] for p in mt["phases"].values()) / 1000
        out.append(f"| {label} | {resumes} | {travel_m:.1f} | {phases} | {mt['estimated_s']:.0f} | "
                   f"{mt['actual_s']:.0f} | {wall:.0f} | {1000 * after['max_position_mm']:.2f} | "
                   f"{1000 * after['rms_position_mm']:.2f} |")
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats, no simulated runs")
    args = parser.parse_args(argv)
    repeats, reps = (3, 20) if args.quick else (7, 100)
    load = os.getloadavg()[0]
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    order = ["| robot | order | leg travel (m) | motion (min) | motion / design | total (min) | solver (s) | "
             "drift absorbed | max corr(t, pose) |", "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    budget = ["| robot | budget | measure poses | estimated total (min) | D-efficiency | predicted verify RMS (µm) | "
              "empirical RMS (µm) | predicted worst pose (µm) | solver (s) |",
              "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for name, robot, timing in robots():
        order += ordering_rows(name, robot, timing, repeats)
        budget += budget_rows(name, robot, timing, (1.0, 0.9, 0.8, 0.7), reps)
    parts = ["## Design order against least-time order", "",
             "The default plan (seed 0: 32 D-optimal poses, one measured 4 times, 24 verify poses measured before and "
             "after the upload), estimated with the station's default `[timing]` for the paper robot and with 20 mm/s, "
             "200 mm/s², 0.2 s settle, 20 s of probing and 0.1 s per move for the small hexapod. Leg travel: sum over "
             "moves of the largest leg change. Drift absorbed: `hilcal.planning.ordering.drift_confounding` of the "
             "measure rows (share of a linear drift's leg signature the geometric model absorbs); max corr: largest "
             "|correlation| of visit time with one pose coordinate.", "", *order, "",
             "## Time-budgeted designs", "",
             "Budgets as fractions of the full least-time plan. Predicted verify RMS: from the least-squares "
             f"covariance with pose noise {NOISE_MM} mm per component; empirical RMS: {reps} LS identifications of "
             "the chosen design from noisy poses (same noise), position error at the 24 verify poses.", "", *budget]
    if not args.quick:
        with tempfile.TemporaryDirectory() as tmp:
            work = Path(tmp)
            stations = ["| simulator | move 1 mm (ms) | move 100 mm (ms) | leg speed (mm/s) | CMM per pose (ms) | "
                        "[timing] |", "|---|---:|---:|---:|---:|---|"]
            for sim_toml in (None, SLOW_SIM):
                timing, row = characterise(sim_toml, work)
                stations.append(row)
            runs = ["| plan | resumes | leg travel (m) | estimated → actual per phase (s) | estimated (s) | "
                    "actual (s) | wall (s) | verify after, max (µm) | RMS (µm) |",
                    "|---|---:|---:|---|---:|---:|---:|---:|---:|"]
            runs += simulated_runs(work, timing)
        parts += ["", "## The simulated station, timed like a real one", "",
                  "Leg moves of 1 and 100 mm and pose measurements through the real drivers on the in-process "
                  "simulator (medians). The default simulator's row is the `SIM_TIMING` of "
                  "`procedures/cli/sim_station.py` (rounded).", "", *stations, "",
                  "## Whole simulated runs, design order against least-time order", "",
                  "`hilcal run --sim --plan P --station T` on the simulator with the servo at time_scale 10 (legs "
                  "500 mm/s), the same seeds for both plans, at nice -10 when run as root; T is the `[timing]` "
                  "measured above. A run stopped by a late heartbeat (a busy machine) is resumed, as an operator "
                  "would; its actual times then include the restart. Estimated → actual "
                  "per phase: measure, verify, verify_after, return_home (s, from report.json). Verify after: the "
                  "measured position error after calibration.", "", *runs]
    body = "\n".join(parts)
    print(body)
    write_doc("benchmarks_machine_time.md", "Machine time: pose order and time budgets",
              "benchmarks/bench_machine_time.py", f"Load average at the start {load:.1f} (wall times grow with it). "
              "See docs/procedure.md (Machine time) for the model.", body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
