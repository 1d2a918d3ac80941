"""`hilcal run` killed with SIGKILL at seeded points (the upload included) and resumed each time.

The station's devices are a simulator that runs on while the runner is killed and started again, as a real machine
and its CMM do when the shop-floor PC's process dies. Every resume must end in a complete run with the full set of
measurements and no duplicates, and the simulated controller's live parameter set and compensation block must always
be exactly the old or the new pair (the rig's transducers have gain errors, so the run uploads a block with the
geometry). A `--sim` run restarts its own simulator on resume: tests/cli/links/test_link_guard.py and the panel's
browser test resume those.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hilcal.protocols.compensation import block_words, zero_block
from hilcal.robot import default_robot
from procedures.station import save_station, station_from_channels
from sim_devices.launcher import spawn_sim_subprocess, stop_sim_subprocess
from tests.cli.sim_speed import INSTANT_SIM, plan_rows

pytestmark = pytest.mark.slow

SIM_CONFIG = INSTANT_SIM + """
[controller.modbus_faults]
response_delay_s = 0.03
[rig.effects.sensor_scale]
enabled = true
gain_error_ppm = [400.0, 0.0, 0.0, -300.0, 0.0, 0.0]
"""
"""Modbus answers slowly enough for kills to land inside the upload; the servo and the CMM work at once and the plan
waits no settle time, so a pose takes about 0.05 s of engine, driver and protocol work (the kill points are in
measurements, not in seconds)."""
POSE_S = 0.05
"""About one pose's time at these settings: a kill lands up to 1.5 poses after its measurement count is reached."""


def _journal_state(path: Path) -> tuple[int, str | None, str | None]:
    """(measurements so far, upload outcome, run_id) read from the journal without disturbing the writer."""
    if not path.exists():
        return 0, None, None
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=1)
        try:
            n = db.execute("SELECT COUNT(*) FROM measurements").fetchone()[0]
            row = db.execute("SELECT value_json FROM steps WHERE key = 'upload'").fetchone()
            run = db.execute("SELECT run_id FROM run").fetchone()
        finally:
            db.close()
    except sqlite3.Error:
        return 0, None, None
    return n, None if row is None else json.loads(row[0])["outcome"], None if run is None else run[0]


def _live_set(state_file: Path) -> tuple[np.ndarray, str | None] | None:
    """The live geometry and compensation block (registers as hex; None: the factory block)."""
    if not state_file.exists():
        return None
    banks = json.loads(state_file.read_text())["banks"]
    return np.array(banks["live"], dtype=float), banks.get("comp_live")


def _start(out: Path, tmp: Path, run_id: str | None, stdout: int = subprocess.DEVNULL) -> subprocess.Popen[bytes]:
    args = ["--resume", run_id] if run_id else ["--station", str(tmp / "station.toml"), "--plan",
                                                str(tmp / "plan.json")]
    env = {**os.environ, "HILCAL_RECORDS": str(tmp / "records.sqlite")}
    return subprocess.Popen([sys.executable, "-m", "procedures.cli", "run", "--yes", "--out", str(out), *args],
                            stdout=stdout, stderr=subprocess.DEVNULL, env=env)


@pytest.mark.timeout(900)
def test_sigkill_at_seeded_points_then_resume(tmp_path, small_plan):
    (tmp_path / "sim.toml").write_text(SIM_CONFIG)
    sim, channels = spawn_sim_subprocess(tmp_path / "sim.toml", ["--state-file", str(tmp_path / "sim_state.json")])
    try:
        save_station(station_from_channels(channels), tmp_path / "station.toml")
        shutil.copy(small_plan, tmp_path / "plan.json")
        _kill_and_resume(tmp_path)
    finally:
        stop_sim_subprocess(sim)


def _kill_and_resume(tmp_path: Path) -> None:
    rng = np.random.default_rng(20261121)
    out = tmp_path / "run"
    journal = out / "journal.sqlite"
    # The small plan: 12 measure poses, one of them measured 4 times; 6 verify poses before and after the upload.
    n_measure, n_verify = plan_rows(tmp_path / "plan.json")
    pre = n_measure + n_verify // 2
    total = n_measure + n_verify
    # Kill points: after k measurements plus a random delay, spread over all three phases, and inside the upload.
    kill_after = sorted(rng.choice(np.arange(1, total), size=8, replace=False).tolist())
    plan = [("startup", 0, rng.uniform(0.5, 2.0))]
    plan += [("measurements", k, rng.uniform(0.0, 1.5 * POSE_S)) for k in kill_after if k < pre]
    plan += [("upload", pre, rng.uniform(0.0, 0.05)), ("upload", pre, rng.uniform(0.05, 0.3))]
    plan += [("measurements", k, rng.uniform(0.0, 1.5 * POSE_S)) for k in kill_after if k >= pre]
    assert len(plan) >= 11

    robot = default_robot()
    old = np.concatenate([robot.a.ravel(), robot.b.ravel(), robot.l0])
    old_block = np.array(block_words(zero_block()), dtype=">u2").tobytes().hex()  # the factory block
    live_sets, counts, run_id, kills = [], [], None, 0
    for kind, k, delay in plan:
        proc = _start(out, tmp_path, run_id)
        t0 = time.monotonic()
        while proc.poll() is None:
            n, upload, rid = _journal_state(journal)
            run_id = run_id or rid
            due = {"startup": time.monotonic() - t0 > delay,
                   "measurements": n >= k,
                   "upload": upload is not None}[kind]
            if due and kind != "startup":
                time.sleep(delay)
            if due and proc.poll() is None:
                proc.send_signal(signal.SIGKILL)
                kills += 1
                break
            time.sleep(0.02)
        proc.wait(30)
        time.sleep(0.3)
        n, _, rid = _journal_state(journal)
        run_id = run_id or rid
        counts.append(n)
        live_sets.append(_live_set(tmp_path / "sim_state.json"))
    assert kills >= 10, f"only {kills} kill points landed before the run finished"
    assert run_id is not None

    final = _start(out, tmp_path, run_id, stdout=subprocess.PIPE)
    stdout = final.communicate(timeout=600)[0].decode()
    assert final.returncode == 0, stdout
    db = sqlite3.connect(journal)
    rows = db.execute("SELECT phase, pose_index FROM measurements ORDER BY seq").fetchall()
    assert len(rows) == total and len(set(rows)) == total
    assert {p for p, _ in rows} == {"measure", "verify", "verify_after"}
    assert counts == sorted(counts), "no measurement is ever lost"
    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "complete" and report["uploaded"] is True
    times = report["machine_time"]
    assert times["interrupted"] is True and times["estimated_s"] > 0
    assert all(times["phases"][p]["actual_s"] is not None for p in ("measure", "verify", "verify_after"))
    assert report["verification"]["after"]["max_position_mm"] <= 0.05
    summary = " ".join(stdout[stdout.index(f"run {run_id}: complete"):].split())  # the resumed run ends with it
    before, after = (report["uncertainty"][when]["max_position_mm"] for when in ("before", "after"))
    assert (f"max position (mm) {before['value']:.4f} ± {before['U']:.4f} {after['value']:.4f} ± {after['U']:.4f}"
            in summary)
    assert "uploaded joint positions a, b and leg offsets l0" in summary
    assert "verdict no acceptance limits set" in summary
    uploaded = report["compensation"]["uploaded_parameters"]
    new = np.concatenate([np.ravel(uploaded["a_mm"]), np.ravel(uploaded["b_mm"]), uploaded["l0_mm"]])
    assert report["compensation"]["compensation_block"]["scale_ppm"][0] == pytest.approx(-400 / 1.0004, abs=15)
    final_live, new_block = _live_set(tmp_path / "sim_state.json")
    assert np.allclose(final_live, new, atol=1e-3) and new_block is not None
    for pair in filter(None, live_sets):
        live, block = pair
        assert (np.allclose(live, old, atol=1e-3) and block == old_block) or (
            np.allclose(live, new, atol=1e-3) and block == new_block), "mixed live set"
