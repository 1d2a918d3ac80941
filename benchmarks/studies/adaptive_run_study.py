"""The adaptive plan at the run level: `hilcal run --sim --adaptive` against the fixed plan on the same simulated rigs.

Why: the in-process study (adaptive_study.py) walks a rig model directly; this one runs the whole `hilcal run` against
the simulated devices on their real transports (controller over CAN and Modbus, CMM over serial, sphere probing, the
approach and repeat rules, the journal, the physics step, the upload), so the issue's criteria are measured on what an
operator runs. Per rig (paper robot; Tables 2-5 and random geometric errors through `[rig] errors`; the configured CMM
noise) four runs: the fixed plan, the fixed plan again with other CMM noise (`[cmm] seed`: how far two equally good
calibrations lie apart), `--adaptive`, and `--adaptive --target-mm` (twice the floor). The floor: the verify maximum of
rigs without geometric errors (`[rig] errors = "zero"`, the controller already right), measured before any upload
(an adaptive run with a budget of the verify phases and a pose or two: it measures the verify poses and stops).
A few rigs with concealed physics (a leg compliance, a 0.3 % scale fault on one leg) check that the adaptive run still
names it, as the fixed plan does.

The station's timing is the default hydraulic one (`procedures.timing.TimingSection`: legs 50 mm/s, 45 s of probing per
pose) with no settle wait, so machine times are those of a real station while the simulated servo and CMM run near
instantly (the wall clock of a run is its computing and protocol work).

Run ``python benchmarks/studies/adaptive_run_study.py [--seeds N] [--physics-seeds N] [--floor-rigs N] [--jobs N]``;
it writes docs/adaptive_run_study.md and the raw results, docs/adaptive_run_study.json (from which ``--from-json``
writes the doc again).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from adaptive_run_study_doc import write_doc

from hilcal.robot import default_robot
from procedures.plan import estimate_plan, make_plan
from procedures.timing import TimingSection
from sim_devices.rig.config import random_errors

ROOT = Path(__file__).resolve().parents[2]
DOC_PATH = ROOT / "docs" / "adaptive_run_study.md"
JSON_PATH = ROOT / "docs" / "adaptive_run_study.json"
SETS = ("table2", "table3", "table4", "table5", "random")
SEED_STRIDE = 100
FLOOR_SEED = 20_000
PHYSICS_SEED = 900
REPLICATE_CMM_SEED = 3_000_000
RANDOM_SIGMA_MM = 0.5
TARGET_FACTOR = 2.0
SIM = """[controller]
time_scale = 100000.0
[cmm]
time_scale = 0.0
[rig.temperature]
drift_k_per_h = 0.0
amplitude_k = 0.0
"""
"""The near-instant simulated devices (as tests/cli/sim_speed.py): machine time is the route estimate."""
PHYSICS = """[rig.effects.sensor_scale]
enabled = true
gain_error_ppm = {gains}
[rig.effects.leg_compliance]
enabled = true
c_mm_per_kn = {compliance}
"""


@dataclass(frozen=True)
class Run:
    """One `hilcal run`: its rig (errors, seed, CMM seed, physics) and the options of the plan."""

    kind: str
    errors: str
    seed: int
    args: tuple[str, ...] = ()
    cmm_seed: int | None = None
    physics: bool = False

    @property
    def name(self) -> str:
        return f"{self.kind}-{self.errors}-{self.seed}"


def _errors_file(work: Path, seed: int) -> Path:
    """Random errors (all 42 from N(0, 0.5 mm²), seeded) as an errors TOML for `[rig] errors`."""
    path = work / f"errors-{seed}.toml"
    legs = random_errors(seed, RANDOM_SIGMA_MM).legs
    path.write_text("".join(f"[[legs]]\nda_mm = {leg.da_mm}\ndb_mm = {leg.db_mm}\ndl0_mm = {leg.dl0_mm}\n"
                            for leg in legs))
    return path


def _config(work: Path, run: Run) -> Path:
    errors = str(_errors_file(work, run.seed)) if run.errors == "random" else run.errors
    text = SIM + f'[rig]\nseed = {run.seed}\nerrors = "{errors}"\n'
    if run.cmm_seed is not None:
        text = text.replace("[cmm]\n", f"[cmm]\nseed = {run.cmm_seed}\n")
    if run.physics:
        gains = [0.0] * 6
        gains[run.seed % 6] = 3000.0
        compliance = 0.004 + 0.002 * ((run.seed * 7919) % 100) / 99  # 4-6 µm/kN, seeded per rig
        text += PHYSICS.format(gains=gains, compliance=round(compliance, 6))
    path = work / f"{run.name}.toml"
    path.write_text(text)
    return path


def _station(work: Path) -> Path:
    values = {**TimingSection().model_dump(), "settle_s": 0.0}
    path = work / "station.toml"
    path.write_text("[timing]\n" + "".join(f"{k} = {v!r}\n" for k, v in values.items()))
    return path


def _verify_phases_min() -> float:
    """The fixed plan's verify phases and way home (min): a floor run's budget is this plus one or two poses, so it
    measures its verify poses before any upload and stops (not identifiable) without identifying."""
    robot = default_robot()
    timing = TimingSection(settle_s=0.0).timing()
    estimate = estimate_plan(make_plan(robot, 0, timing=timing), robot, timing)
    return (estimate.total_s - estimate.phase("measure").total_s) / 60.0


def _result(run: Run, out: Path, code: int, wall_s: float) -> dict[str, Any]:
    """The figures of one run's report.json."""
    report = json.loads((out / "report.json").read_text())
    measure = report["machine_time"]["phases"]["measure"]
    after = (report["verification"] or {}).get("after") or {}
    a = report.get("adaptive") or {}
    return {"kind": run.kind, "errors": run.errors, "seed": run.seed, "code": code, "wall_s": wall_s,
            "status": report["status"], "rows": report["method"]["n_measure_rows"] if "method" in report else None,
            "measure_s": measure["estimated_s"], "total_s": report["machine_time"]["estimated_s"],
            "before_max_mm": report["verification"]["before"]["max_position_mm"],
            "after_max_mm": after.get("max_position_mm"), "effects": (report.get("physics") or {}).get("effects"),
            "stop": a.get("kind"), "n_rows": a.get("n_rows"), "prediction": a.get("prediction"),
            "within_prediction": (a.get("verification") or {}).get("within_prediction"),
            "suspected": (a.get("screening") or {}).get("suspected"), "summary": a.get("summary")}


def run_all(runs: list[Run], work: Path, jobs: int) -> list[dict[str, Any]]:
    """Every run, `jobs` at a time, each in its own folder and records file; the results in the given order."""
    station = _station(work)
    pending = list(enumerate(runs))
    active: dict[int, tuple[subprocess.Popen[bytes], Path, float]] = {}
    results: list[dict[str, Any] | None] = [None] * len(runs)
    while pending or active:
        while pending and len(active) < jobs:
            i, run = pending.pop(0)
            out = work / run.name
            env = {**os.environ, "HILCAL_RECORDS": str(work / f"{run.name}.sqlite"), "OPENBLAS_NUM_THREADS": "1"}
            cmd = [sys.executable, "-m", "procedures.cli", "run", "--sim", "--yes", "--operator", "bench",
                   "--sim-config", str(_config(work, run)), "--station", str(station), "--station-timing",
                   "--out", str(out), *run.args]
            log = (work / f"{run.name}.log").open("w")
            active[i] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env), out,
                         time.perf_counter())
        for i, (proc, out, t0) in list(active.items()):
            if proc.poll() is None:
                continue
            del active[i]
            if not (out / "report.json").exists():
                raise RuntimeError(f"{runs[i].name} wrote no report (exit {proc.returncode}): see "
                                   f"{work / runs[i].name}.log")
            results[i] = _result(runs[i], out, proc.returncode, time.perf_counter() - t0)
            shutil.rmtree(out, ignore_errors=True)
            print(f"{sum(r is not None for r in results)}/{len(runs)} {runs[i].name}: "
                  f"{results[i]['after_max_mm']}", file=sys.stderr, flush=True)
        time.sleep(0.2)
    return [r for r in results if r is not None]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10, help="rig seeds per error set (the issue: 10)")
    parser.add_argument("--physics-seeds", type=int, default=5, help="rigs with concealed physics")
    parser.add_argument("--floor-rigs", type=int, default=10, help="error-free rigs for the floor")
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="runs at once")
    parser.add_argument("--json", type=Path, default=JSON_PATH, help="where the raw results go (default: "
                        "docs/adaptive_run_study.json, from which --from-json writes the doc again)")
    parser.add_argument("--quick", action="store_true", help="two seeds per set, one physics rig, four floor rigs")
    parser.add_argument("--from-json", type=Path, help="write the doc again from the raw results of an earlier run")
    args = parser.parse_args(argv)
    if args.from_json:
        saved = json.loads(args.from_json.read_text())
        DOC_PATH.write_text(write_doc(saved["results"], saved["context"]))
        return 0
    if args.quick:
        args.seeds, args.physics_seeds, args.floor_rigs = 2, 1, 4
    command = ("python benchmarks/studies/adaptive_run_study.py" + "".join(
        f" --{k.replace('_', '-')} {v}" for k, v in (("seeds", args.seeds), ("physics_seeds", args.physics_seeds),
                                                     ("floor_rigs", args.floor_rigs)) if v != parser.get_default(k)))
    default_robot()  # the robot file must load before anything starts
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="hilcal-adaptive-runs-") as tmp:
        work = Path(tmp)
        floor_args = ("--adaptive", "--max-minutes", f"{_verify_phases_min() + 1.5:.2f}")
        floor_runs = run_all([Run("floor", "zero", FLOOR_SEED + k, floor_args) for k in range(args.floor_rigs)],
                             work, args.jobs)
        floors = sorted(r["before_max_mm"] for r in floor_runs)
        floor_mm = statistics.median(floors)
        target_mm = round(TARGET_FACTOR * floor_mm, 6)
        runs = []
        for k, errors in enumerate(SETS):
            for s in range(args.seeds):
                seed = SEED_STRIDE * k + s
                runs += [Run("fixed", errors, seed), Run("adaptive", errors, seed, ("--adaptive",)),
                         Run("target", errors, seed, ("--adaptive", "--target-mm", str(target_mm))),
                         Run("replicate", errors, seed, cmm_seed=seed + REPLICATE_CMM_SEED)]
        for s in range(args.physics_seeds):
            runs += [Run("physics_fixed", "table2", PHYSICS_SEED + s, physics=True),
                     Run("physics_adaptive", "table2", PHYSICS_SEED + s, ("--adaptive",), physics=True)]
        results = run_all(runs, work, args.jobs)
    elapsed = time.perf_counter() - t0
    context = {"command": command, "elapsed_s": elapsed, "jobs": args.jobs, "floor_mm": floor_mm,
               "floors_mm": floors, "target_mm": target_mm, "seeds": args.seeds, "physics_seeds": args.physics_seeds,
               "timing": {**TimingSection().model_dump(), "settle_s": 0.0}}
    args.json.write_text(json.dumps({"context": context, "floor": floor_runs, "results": results}, indent=1) + "\n")
    DOC_PATH.write_text(write_doc(results, context))
    print(f"wrote {DOC_PATH} ({elapsed:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
