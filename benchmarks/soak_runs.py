"""One soak run: a full `hilcal run --sim --yes` under one disturbance, then what its journal and the simulator
say about it (completed or why not, measurements lost or duplicated, the controller's live parameter set,
commands received while the link was down, the calibrated verification error).

Used by `bench_soak.py` (the full table) and by tests/test_soak.py (a few runs in `make test`).
"""

from __future__ import annotations

import json
import os
import random
import signal
import sqlite3
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np


def expected_rows(plan_file: Path) -> set[tuple[str, int]]:
    """The rows a completed run of the plan it kept (``plan.json``) journals: every measure pose with its repeats
    (the default plan: 32 design poses, one measured 4 times, 35 rows) and the verify poses before and after."""
    plan = json.loads(plan_file.read_text())
    n_measure, n_verify = len(plan["measure_poses"]), len(plan["verify_poses"])
    return {("measure", k) for k in range(n_measure)} | {(p, k) for p in ("verify", "verify_after")
                                                         for k in range(n_verify)}


LATE_S = 0.1
"""The station's heartbeat_timeout_s: after this silence the host sends nothing but an e-stop."""
IN_FLIGHT_S = 0.1
"""Frames already on their way when the host noticed (pty buffers, a busy computer)."""
HOST_ESTOP_FRAME = 16
"""EstopRequest (controller.dbc): the one frame a host may send while the link is down."""
HOG = "import time\nend = time.monotonic() + {seconds}\nwhile time.monotonic() < end:\n    pass\n"


@dataclass(frozen=True)
class Condition:
    """A disturbance: simulator settings (seeded), CPU hogs, and SIGKILLs of the runner."""

    name: str
    title: str
    hogs: int = 0
    kills: int = 0

    def sim_config(self, seed: int, work: Path, gaps_per_min: float = 20.0) -> str:
        rng = random.Random(seed * 7 + len(self.name))
        lines = ["[rig]", f"seed = {seed}", "[controller.can_faults]", f'gap_log = "{work / "gaps.jsonl"}"']
        if self.name == "heartbeat_gaps":
            lines += [f"gaps_per_min = {gaps_per_min}", "gap_min_s = 0.05", "gap_max_s = 0.5", f"seed = {seed}"]
        if self.name == "modbus_drops":
            lines += ["[controller.modbus_faults]", f"drop_after_writes = {rng.randint(1, 5)}",
                      f"execute_dropped_write = {'true' if rng.random() < 0.5 else 'false'}"]
        if self.name == "cmm_faults":
            lines += ["[cmm.faults]", "silence = 0.003", "garbage = 0.02"]
        return "\n".join(lines) + "\n"


CONDITIONS = (
    Condition("undisturbed", "none (the reference of each seed)"),
    Condition("cpu_hogs", "two busy-loop processes, one per core, for the whole run", hogs=2),
    Condition("heartbeat_gaps", "link gaps of 0.05-0.5 s at random times (20 per minute): no controller frame"),
    Condition("cmm_faults", "CMM silence (0.3 %: a command never acknowledged) and garbage lines (2 %) per command"),
    Condition("modbus_drops", "Modbus connection dropped at a random write of the upload (executed or not)"),
    Condition("sigkill_resume", "SIGKILL of the runner at a random time, then the printed resume, twice", kills=2),
)


@dataclass
class SoakRun:
    condition: str
    seed: int
    exit_codes: list[int] = field(default_factory=list)
    completed: bool = False
    abort_reason: str | None = None
    wall_s: float = 0.0
    rows: int = 0
    lost: int = 0
    duplicated: int = 0
    live_set: str = "unknown"
    late_commands: int = 0
    gaps: int = 0
    holds: dict[str, int] = field(default_factory=dict)
    held_s: float = 0.0
    verify_after_max_mm: float | None = None

    def to_json(self) -> dict:
        return asdict(self)


def _query(journal: Path, sql: str) -> list[tuple]:
    db = sqlite3.connect(f"file:{journal}?mode=ro", uri=True, timeout=5)
    try:
        return db.execute(sql).fetchall()
    finally:
        db.close()


def _start(args: list[str], work: Path, attempt: int) -> tuple[subprocess.Popen[bytes], Path]:
    """The runner in the background, its output in files (a pipe nobody reads could block it)."""
    env = {**os.environ, "HILCAL_RECORDS": str(work / "records.sqlite"), "MPLBACKEND": "Agg"}
    err = work / f"stderr-{attempt}.txt"
    with (work / f"stdout-{attempt}.txt").open("wb") as stdout, err.open("wb") as stderr:
        proc = subprocess.Popen([sys.executable, "-m", "procedures.cli", "run", "--yes", *args], env=env,
                                stdout=stdout, stderr=stderr)
    return proc, err


def _hogs(n: int, seconds: float) -> list[subprocess.Popen[bytes]]:
    return [subprocess.Popen([sys.executable, "-c", HOG.format(seconds=seconds)]) for _ in range(n)]


def _run_id(out: Path) -> str | None:
    try:
        rows = _query(out / "journal.sqlite", "SELECT run_id FROM run")
    except sqlite3.Error:
        return None
    return rows[0][0] if rows else None


def soak_run(condition: Condition, seed: int, work: Path, *, kill_window_s: tuple[float, float] = (4.0, 60.0),
             timeout_s: float = 900.0, extra_sim_config: str = "", gaps_per_min: float = 20.0,
             extra_run_args: tuple[str, ...] = ()) -> SoakRun:
    """One full run (resumed after each SIGKILL) and its bookkeeping; never raises for a failed run.

    ``extra_sim_config`` is appended to the condition's simulator TOML (the tests run the servo and the CMM at once:
    their checks count what happened, not how long it took); ``gaps_per_min`` sets how often the link gaps come;
    ``extra_run_args`` go to the new run's command line (the tests pass a plan made once)."""
    work.mkdir(parents=True, exist_ok=True)
    (work / "sim.toml").write_text(condition.sim_config(seed, work, gaps_per_min) + extra_sim_config)
    out = work / "run"
    rng = random.Random(1000 + seed)
    result = SoakRun(condition.name, seed)
    hogs = _hogs(condition.hogs, timeout_s)
    t0 = time.monotonic()
    new_run = ["--sim", "--sim-config", str(work / "sim.toml"), "--seed", str(seed), "--out", str(out),
               *extra_run_args]
    try:
        args = new_run
        for attempt in range(condition.kills + 1):
            proc, err = _start(args, work, attempt)
            if attempt < condition.kills:
                try:
                    proc.wait(rng.uniform(*kill_window_s))
                except subprocess.TimeoutExpired:
                    proc.send_signal(signal.SIGKILL)
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            stderr = err.read_text(errors="replace")
            result.exit_codes.append(proc.returncode)
            if proc.returncode == 0:
                result.completed = True
                break
            if proc.returncode != -signal.SIGKILL:  # stopped by itself: an abort, reported as it is
                result.abort_reason = (stderr.strip().splitlines() or ["(no message)"])[-1][:300]
                break
            run_id = _run_id(out)
            args = new_run if run_id is None else ["--resume", run_id, "--out", str(out)]
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
    result.wall_s = time.monotonic() - t0
    _inspect(result, work, out)
    return result


def _inspect(result: SoakRun, work: Path, out: Path) -> None:
    journal = out / "journal.sqlite"
    if journal.exists():
        rows = _query(journal, "SELECT phase, pose_index FROM measurements")
        result.rows = len(rows)
        result.duplicated = len(rows) - len(set(rows))
        result.lost = len(expected_rows(out / "plan.json") - set(rows)) if result.completed else 0
        for (data,) in _query(journal, "SELECT data_json FROM events WHERE kind = 'link_hold'"):
            link = json.loads(data)["link"]
            result.holds[link] = result.holds.get(link, 0) + 1
        result.held_s = sum(json.loads(d)["held_s"] for (d,) in
                            _query(journal, "SELECT data_json FROM events WHERE kind = 'link_recovered'"))
        upload = _query(journal, "SELECT value_json FROM steps WHERE key = 'upload'")
        report = out / "report.json"
        uploaded = (json.loads(report.read_text())["compensation"].get("uploaded_parameters")
                    if result.completed and report.exists() else None)
        result.live_set = _live_set_state(out / "sim_state.json", json.loads(upload[0][0]) if upload else None,
                                          uploaded)
    gaps_path = work / "gaps.jsonl"
    if gaps_path.exists():
        records = [json.loads(line) for line in gaps_path.read_text().splitlines()]
        result.gaps = sum(r["event"] == "gap" for r in records)
        result.late_commands = sum(r["event"] == "received_in_gap" and r["frame_id"] != HOST_ESTOP_FRAME
                                   and r["into_gap_s"] > LATE_S + IN_FLIGHT_S for r in records)
    report = out / "report.json"
    if result.completed and report.exists():
        after = json.loads(report.read_text())["verification"]["after"]
        result.verify_after_max_mm = None if after is None else after["max_position_mm"]


def _vector(params: dict) -> np.ndarray:
    return np.concatenate([np.ravel(params["a_mm"]), np.ravel(params["b_mm"]), np.ravel(params["l0_mm"])])


def _live_set_state(state_file: Path, upload: dict | None, uploaded: dict | None) -> str:
    """The simulator's live set: "previous", "new" (the report's uploaded set), or "half-written" if neither."""
    if not state_file.exists():
        return "unknown"
    live = np.array(json.loads(state_file.read_text())["banks"]["live"], dtype=float).ravel()
    if upload is None:
        return "previous (no upload started)"
    if np.allclose(live, _vector(upload["previous"]), atol=1e-3):
        return "previous"
    if uploaded is not None and np.allclose(live, _vector(uploaded), atol=1e-3):
        return "new"
    return "half-written" if uploaded is not None else "not previous (run incomplete: unverified)"
