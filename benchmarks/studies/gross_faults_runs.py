"""The gross-faults study's cases and one case's run: a whole `hilcal run --sim --yes` of a badly set-up machine.

A case is a robot (the paper robot, `examples/hexapod_small.toml`, `examples/hexapod_stroke320.toml`) and a fault
on the simulated rig: one or two legs' transducer gradient wrong by 0.5-9 %, every joint and leg offset off by
N(0, s) with s 1-4 mm, the CMM station's published alignment off by 5-50 mm, or a dead transducer. Each robot also
runs its healthy rig (the simulator's defaults: the paper's Table 2 errors mapped onto the robot, a 2 mm alignment
error), which the faulty runs are compared with. Every run uses rig seed 1 and near-instant devices, as the other
run-level studies do; the simulated CMM keeps its own machine clock all the same, which sim.log's `cmm_sim.stopped`
line gives, and every measured pose's journal row says how many touches and searches it took.

``run_case(case, work)`` runs one case in its own folder and returns its figures (a test can call it on one
case); ``summarize(run_dir, code, output)`` reads them from a finished run's folder.
"""

from __future__ import annotations

import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from fnmatch import fnmatch
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
ROBOTS: dict[str, Path | None] = {"paper": None, "small": ROOT / "examples" / "hexapod_small.toml",
                                  "stroke320": ROOT / "examples" / "hexapod_stroke320.toml"}
"""The robots: None is the built-in paper Table 1 robot."""
ROBOT_LABELS = {"paper": "paper robot (built-in Table 1)",
                "small": "small electric hexapod (examples/hexapod_small.toml, 40 mm stroke)",
                "stroke320": "electric hexapod with 320 mm of stroke (examples/hexapod_stroke320.toml)"}
RIG_SEED = 1
FAST: dict[str, Any] = {"controller": {"time_scale": 100000.0}, "cmm": {"time_scale": 0.0},
                        "rig": {"temperature": {"drift_k_per_h": 0.0, "amplitude_k": 0.0}}}
"""The near-instant servo and CMM of the other run-level studies (physics_study.py, adaptive_run_study.py): the run
costs its engine, driver and protocol work; the rig's temperature is held (its clock follows the servo's). The
simulated CMM's machine clock is not scaled: `cmm_sim.stopped ... machine_time_s` in sim.log is what its commands
would have taken (docs/protocols.md, CMM simulator)."""
GRADIENTS_PCT = (0.5, 1.0, 2.0, 4.0, 6.0, 9.0)
ONE_LEG = {0: 1.0}
"""One leg: leg 1 reads long (reported stroke = true stroke x (1 + g))."""
TWO_LEGS = {0: 1.0, 3: -1.0}
"""Two legs: leg 1 reads long and leg 4 (on another base pair) short, by the same amount."""
ASSEMBLY_MM = (1.0, 2.0, 3.0, 4.0)
ASSEMBLY_SEED = 33
"""Assembly errors: all 42 (da, db per joint coordinate, dl0 per leg) from N(0, s^2), sim_devices.rig.config.
random_errors(ASSEMBLY_SEED + k, s), k the size's index; the same draws on every robot."""
ALIGNMENT_MM = (5.0, 10.0, 20.0, 50.0)
DRIVE_ROBOTS = ("stroke320",)
DRIVE_GAIN_PPM = 60000.0
"""Scale fault with a drive compliance (issue 38): leg 1 reads 6 % long, as on the diagnosed 320 mm hexapod..."""
DRIVE_C_MM_PER_KN_M = (0.30, 0.35, 0.40, 0.45, 0.50, 0.55)
"""... and every leg's drive sags under its load by 300-550 µm/kN per metre of stroke (the rig's drive_compliance
c_per_length, with no fixed part and no free length at zero stroke, as the twin `hilcal diagnose --report` writes)."""
SOFT_DRIVE_FACTOR = 150.0
"""The same drives this many times softer (45-82.5 mm/(kN m), 4-20 times a belt drive's): a sag of millimetres that
changes with the pose, which the run's model (geometry and reading scales) does not hold; where the crash showed."""
DEAD_LEGS = [4]
COLLISION_EVENT = "cmm_sim.collision"
STOPPED_EVENT = "cmm_sim.stopped"
MACHINE_TIME = re.compile(r"\bmachine_time_s=([-+0-9.eE]+)")
ANSI = re.compile(r"\x1b\[[0-9;]*m")
"""The simulator's log (structlog's console lines, perhaps coloured): the colour codes are dropped before reading."""
RUN_TIMEOUT_S = 1800.0
QUICK = ("*/healthy", "*/gradient-1leg-4pc", "paper/assembly-3mm", "paper/alignment-20mm", "paper/dead-transducer")
RUN_LINE = re.compile(r"^run \d{8}T\d{6}Z-[0-9a-f]+:? (.+)$", re.MULTILINE)
RESUME_TAIL = re.compile(r"\s*The journal is kept; continue with: .*$")


@dataclass(frozen=True)
class Case:
    """One run: the robot's key, the fault's name and label, and the simulator sections it adds to FAST."""

    robot: str
    name: str
    kind: str
    label: str
    sim: dict[str, Any] = field(default_factory=dict)
    assembly_sigma_mm: float | None = None
    assembly_seed: int | None = None

    @property
    def id(self) -> str:
        return f"{self.robot}/{self.name}"


def _gains(legs: dict[int, float], pct: float) -> list[float]:
    ppm = [0.0] * 6
    for leg, sign in legs.items():
        ppm[leg] = sign * pct * 1e4
    return ppm


def _pc(value: float) -> str:
    return f"{value:g}".replace(".", "_") if value != int(value) else f"{int(value)}"


def cases(robots: Iterable[str] = tuple(ROBOTS)) -> list[Case]:
    """Every case, robot by robot, the healthy rig first."""
    out: list[Case] = []
    for robot in robots:
        out.append(Case(robot, "healthy", "healthy", "healthy rig (simulator defaults)"))
        for legs, tag, said in ((ONE_LEG, "1leg", "leg 1 +{p} %"), (TWO_LEGS, "2legs", "leg 1 +{p} %, leg 4 -{p} %")):
            for pct in GRADIENTS_PCT:
                effect = {"sensor_scale": {"enabled": True, "gain_error_ppm": _gains(legs, pct)}}
                out.append(Case(robot, f"gradient-{tag}-{_pc(pct)}pc", "gradient",
                                "gradient " + said.format(p=f"{pct:g}"), {"rig": {"effects": effect}}))
        for k, sigma in enumerate(ASSEMBLY_MM):
            out.append(Case(robot, f"assembly-{_pc(sigma)}mm", "assembly", f"assembly N(0, {sigma:g} mm)",
                            assembly_sigma_mm=sigma, assembly_seed=ASSEMBLY_SEED + k))
        for mm in ALIGNMENT_MM:
            out.append(Case(robot, f"alignment-{_pc(mm)}mm", "alignment", f"station alignment off {mm:g} mm",
                            {"cmm": {"alignment_error_mm": mm}}))
        if robot in DRIVE_ROBOTS:
            out += [_drive_case(robot, 1.0), _drive_case(robot, SOFT_DRIVE_FACTOR)]
        out.append(Case(robot, "dead-transducer", "dead", f"dead transducer (leg {DEAD_LEGS[0]})",
                        {"controller": {"dead_transducer_legs": DEAD_LEGS}}))
    return out


def _drive_case(robot: str, factor: float) -> Case:
    """Leg 1 reading 6 % long and every leg's drive compliance, `factor` times DRIVE_C_MM_PER_KN_M."""
    c = [factor * v for v in DRIVE_C_MM_PER_KN_M]
    effects = {"sensor_scale": {"enabled": True, "gain_error_ppm": _gains(ONE_LEG, DRIVE_GAIN_PPM / 1e4)},
               "drive_compliance": {"enabled": True, "c_fixed_mm_per_kn": 0.0, "c_per_length_mm_per_kn_m": c,
                                    "free_length_at_zero_stroke_mm": 0.0}}
    soft = factor != 1.0
    return Case(robot, "gradient-1leg-6pc-soft-drive" if soft else "gradient-1leg-6pc-drive",
                "soft-drive" if soft else "drive",
                f"gradient leg 1 +6 %, drive compliance {c[0]:g}-{c[-1]:g} mm/(kN m)"
                + (f" ({factor:g}x softer)" if soft else " (issue 38's twin)"), {"rig": {"effects": effects}})


def select(all_cases: list[Case], patterns: Iterable[str]) -> list[Case]:
    """The cases whose id matches any glob (e.g. ``paper/*``, ``*/gradient-1leg-*``), with each chosen robot's
    healthy case, which the extra probing time is measured against."""
    pats = [p.strip() for p in patterns if p.strip()]
    chosen = {c.id for c in all_cases if any(fnmatch(c.id, p) for p in pats)}
    chosen |= {f"{c.robot}/healthy" for c in all_cases if c.id in chosen}
    return [c for c in all_cases if c.id in chosen]


def _merge(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    out = dict(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def sim_toml(case: Case, errors_file: Path | None = None) -> str:
    """The simulator configuration of a case: its robot, rig seed (and errors), the fault, the fast devices."""
    from hilcal.protocols.toml_text import toml_lines

    data: dict[str, Any] = {}
    if ROBOTS[case.robot] is not None:
        data["robot"] = str(ROBOTS[case.robot])
    rig: dict[str, Any] = {"seed": RIG_SEED}
    if errors_file is not None:
        rig["errors"] = str(errors_file)
    data = _merge(_merge({**data, "rig": rig}, FAST), case.sim)
    return "\n".join(toml_lines(data)).strip() + "\n"


def write_assembly_errors(case: Case, folder: Path) -> Path:
    """The case's assembly errors as an errors TOML (sim_devices.rig.config.load_errors reads it)."""
    from sim_devices.rig.config import errors_toml, random_errors

    assert case.assembly_sigma_mm is not None and case.assembly_seed is not None
    path = folder / "errors.toml"
    path.write_text(errors_toml(random_errors(case.assembly_seed, case.assembly_sigma_mm),
                                f"{case.label}: random_errors({case.assembly_seed}, {case.assembly_sigma_mm})"))
    return path


def command(case: Case, folder: Path) -> list[str]:
    """The `hilcal run` of a case (its robot both as --robot and in the simulator's configuration)."""
    robot = ROBOTS[case.robot]
    return [sys.executable, "-m", "procedures.cli", "run", "--sim", "--yes", "--operator", "study",
            "--sim-config", str(folder / "sim.toml"), "--out", str(folder / "run"),
            "--records", str(folder / "records.sqlite"), *(["--robot", str(robot)] if robot else [])]


def final_words(output: str) -> str:
    """What the run said: its final message's first line (`run ID complete`, `run ID stopped: ...`) without the run
    id and the resume hint; else the last line it printed."""
    found = RUN_LINE.findall(output)
    if found:
        return RESUME_TAIL.sub("", found[0].strip())
    lines = [line.strip() for line in output.splitlines() if line.strip()]
    return lines[-1] if lines else ""


def _journal(run_dir: Path) -> tuple[str | None, dict[str, int], list[dict[str, Any]]]:
    """The journal's run status, its measured rows per phase and every measured row's detail (read only)."""
    path = run_dir / "journal.sqlite"
    if not path.exists():
        return None, {}, []
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        row = db.execute("SELECT status FROM run").fetchone()
        rows = dict(db.execute("SELECT phase, COUNT(*) FROM measurements GROUP BY phase").fetchall())
        details = [json.loads(d or "{}") for (d,) in db.execute("SELECT detail_json FROM measurements ORDER BY seq")]
    except (sqlite3.Error, ValueError):
        return None, {}, []
    finally:
        db.close()
    return (row[0] if row else None), rows, details


def probing(details: list[dict[str, Any]]) -> dict[str, Any]:
    """The CMM's work per measured pose from the journal rows' detail (drivers/cmm/probing.py writes `touches`,
    `searched_spheres`, `search_touches` and `largest_search_offset_mm` with every measured pose): the touches per
    pose, the spheres searched for, the touches of those searches and the largest offset a search found a sphere at,
    over the rows that carry them (None when none does)."""
    rows = [d for d in details if isinstance(d, dict) and "touches" in d]
    if not rows:
        return {"touches_per_pose": None, "searched_spheres": None, "search_touches": None,
                "largest_search_offset_mm": None, "detail_rows": 0}
    return {"touches_per_pose": sum(float(d["touches"]) for d in rows) / len(rows),
            "searched_spheres": sum(int(d.get("searched_spheres") or 0) for d in rows),
            "search_touches": sum(int(d.get("search_touches") or 0) for d in rows),
            "largest_search_offset_mm": max(float(d.get("largest_search_offset_mm") or 0.0) for d in rows),
            "detail_rows": len(rows)}


def _pre_upload_rows(run_dir: Path) -> list[dict[str, Any]]:
    """The journal's rows before the upload (measure, verify), in the order measured: cmd, legs, meas."""
    path = run_dir / "journal.sqlite"
    if not path.exists():
        return []
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        found = db.execute("SELECT cmd_json, legs_json, meas_json FROM measurements WHERE phase IN "
                           "('measure', 'verify') ORDER BY seq").fetchall()
    except sqlite3.Error:
        return []
    finally:
        db.close()
    return [{"cmd": json.loads(c), "legs": json.loads(legs), "meas": json.loads(m)} for c, legs, m in found]


def prediction_check(run_dir: Path, robot_key: str) -> dict[str, Any]:
    """How the run's predictions held, from the journal: its model (procedures.acquisition) taught the rows before
    the upload one by one, as the run taught it, each platform sphere predicted as the CMM driver predicts it
    (drivers/cmm/probing.py: the platform frame from the predicted pose on the registered base, conditioned on the
    spheres measured before it) against where the measured pose put it. The largest offset over its bound, the most
    an offset exceeded its bound (mm), and the rows with a sphere beyond its bound; None when no row was measured."""
    import numpy as np

    from drivers.cmm.probing import MEASURED_SIGMA_MM, REGISTERED_DEG, REGISTERED_MM
    from drivers.cmm.types import ProbingConfig, transform_from_pose
    from hilcal.acquisition.spheres import BodyBelief
    from hilcal.robot import default_robot, load_robot
    from procedures.acquisition import Acquisition

    rows = _pre_upload_rows(run_dir)
    if not rows:
        return {"sphere_over_bound": None, "sphere_beyond_mm": None, "rows_beyond_bound": None}
    robot = default_robot() if ROBOTS[robot_key] is None else load_robot(ROBOTS[robot_key])
    floor, up = ProbingConfig().least_bound_mm, np.array([0.0, 0.0, 1.0])
    acq = Acquisition.start(robot, robot.a, robot.b, robot.l0, [])
    ratios, beyond = [], []
    for row in rows:
        expected = acq.expect(np.asarray(row["legs"]), np.asarray(row["cmd"]))
        if expected is not None:
            platform = BodyBelief.within(np.eye(4), REGISTERED_MM, REGISTERED_DEG).composed(
                transform_from_pose(expected.pose), expected.cov)
            T = transform_from_pose(np.asarray(row["meas"]))
            over = []
            for s in robot.platform_spheres:
                pred = platform.predict(s, up, floor)
                centre = T[:3, :3] @ s + T[:3, 3]
                offset = float(np.linalg.norm(centre - pred.centre_mm))
                over.append((offset / pred.bound_mm, offset - pred.bound_mm))
                platform = platform.condition(s, centre, MEASURED_SIGMA_MM)
            ratios.append(max(o[0] for o in over))
            beyond.append(max(o[1] for o in over))
        acq.learn(row)
    return {"sphere_over_bound": max(ratios), "sphere_beyond_mm": max(beyond),
            "rows_beyond_bound": sum(b > 0.0 for b in beyond)}


def _sim_log(run_dir: Path) -> list[str] | None:
    log = run_dir / "sim.log"
    return ANSI.sub("", log.read_text(errors="replace")).splitlines() if log.exists() else None


def count_collisions(run_dir: Path) -> int | None:
    """COLLISION_EVENT lines in the run's sim.log; None when the run wrote no sim.log."""
    lines = _sim_log(run_dir)
    return None if lines is None else sum(COLLISION_EVENT in line for line in lines)


def cmm_machine_time(run_dir: Path) -> float | None:
    """The simulated CMM's machine clock when it stopped: `machine_time_s` of STOPPED_EVENT in the run's sim.log
    (the sum of every command's unscaled duration); None when the log has no such line."""
    found = [m.group(1) for line in _sim_log(run_dir) or () if STOPPED_EVENT in line
             for m in [MACHINE_TIME.search(line)] if m]
    return float(found[-1]) if found else None


def summarize(run_dir: Path, code: int | None, output: str, robot_key: str | None = None) -> dict[str, Any]:
    """A finished run's figures from its folder: report.json (status, verification after, the physics step's
    prediction), the journal (status, rows per phase, the CMM's work per pose and, given the robot, how the
    predictions held: ``prediction_check``), sim.log (collisions and the CMM's machine time) and what it printed."""
    report_path = run_dir / "report.json"
    report = json.loads(report_path.read_text()) if report_path.exists() else {}
    status, rows, details = _journal(run_dir)
    phases = (report.get("machine_time") or {}).get("phases") or {}
    measure = phases.get("measure") or {}
    physics = report.get("physics") or {}
    verification = report.get("verification") or {}
    machine_s = cmm_machine_time(run_dir)
    n_rows = sum(rows.values())
    return {
        "code": code, "status": report.get("status") or status, "report": bool(report), "rows": rows,
        "said": final_words(output), "collisions": count_collisions(run_dir),
        "cmm_machine_s": machine_s, "cmm_s_per_pose": machine_s / n_rows if machine_s is not None and n_rows else None,
        **probing(details), **(prediction_check(run_dir, robot_key) if robot_key is not None else {}),
        "measure_actual_s": measure.get("actual_s"), "measure_poses_planned": measure.get("n_poses"),
        "before": verification.get("before"), "after": verification.get("after"),
        "predicted": physics.get("predicted_with_physics"), "geometry_only": physics.get("predicted_geometry_only"),
        "effects": physics.get("effects") or [], "block": bool(physics.get("block")),
        "noise_mm": physics.get("noise_mm"), "warnings": report.get("warnings") or [],
        "tail": output[-1500:] if code not in (0, 4) else "",
    }


def _stop(proc: subprocess.Popen[str]) -> None:
    """Stop a run that outlived its time as an operator would (Ctrl-C, then kill), by its process id."""
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def run_case(case: Case, work: Path, timeout_s: float = RUN_TIMEOUT_S) -> dict[str, Any]:
    """Run one case as `hilcal run --sim --yes` in ``work/<robot>__<name>`` and return its figures.

    The keys: the case (id, robot, name, kind, label), the exit code, the ``summarize`` figures, the wall-clock
    seconds and the command."""
    head = {"id": case.id, "robot": case.robot, "name": case.name, "kind": case.kind, "label": case.label}
    folder = work / case.id.replace("/", "__")
    folder.mkdir(parents=True, exist_ok=True)
    errors = write_assembly_errors(case, folder) if case.assembly_sigma_mm is not None else None
    (folder / "sim.toml").write_text(sim_toml(case, errors))
    cmd = command(case, folder)
    env = {**os.environ, "MPLBACKEND": "Agg", "OPENBLAS_NUM_THREADS": "1", "COLUMNS": "200"}
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    timed_out = False
    try:
        output, _ = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        timed_out = True
        _stop(proc)
        output, _ = proc.communicate()
    (folder / "output.txt").write_text(output)
    result = {**head, **summarize(folder / "run", proc.returncode, output, case.robot),
              "seconds": time.perf_counter() - t0, "timed_out": timed_out,
              "command": "hilcal " + " ".join(cmd[3:]).replace(str(folder), "DIR")}
    if timed_out:
        result["said"] = f"timed out after {timeout_s:.0f} s (stopped with Ctrl-C): {result['said']}"
    return result
