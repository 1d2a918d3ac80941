"""`hilcal run --sim --adaptive` killed with SIGKILL at seeded measurement counts inside the adaptive measure phase and
resumed each time: it continues with the same choices.

The killed run and an uninterrupted one with the same seeds (plan, rig) run at once, each until its measure phase has
stopped (the journal's `adaptive_stop` checkpoint; what follows is the fixed plan's path, tested elsewhere). Their
commanded poses and stops must be equal, and a replay of the killed run's journal must choose every pose it chose.
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

from tests.cli.sim_speed import INSTANT_SIM, instant_timing

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]


def _journal(path: Path) -> tuple[list[list[float]], dict | None, str | None]:
    """(commanded measure poses in order, the adaptive stop, run_id), read without disturbing the writer."""
    if not path.exists():
        return [], None, None
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=1)
        try:
            rows = db.execute("SELECT pose_index, cmd_json FROM measurements WHERE phase = 'measure' ORDER BY seq"
                              ).fetchall()
            stop = db.execute("SELECT value_json FROM steps WHERE key = 'checkpoint:adaptive_stop'").fetchone()
            run = db.execute("SELECT run_id FROM run").fetchone()
        finally:
            db.close()
    except sqlite3.Error:
        return [], None, None
    assert [k for k, _ in rows] == list(range(len(rows))), "no measure row lost or measured twice"
    return [json.loads(c) for _, c in rows], None if stop is None else json.loads(stop[0]), run and run[0]


def _start(tmp: Path, out: Path, run_id: str | None) -> subprocess.Popen[bytes]:
    """A new adaptive run or a resume of run_id. The reference plan is tests/cli/conftest.py's calibration plan: the
    claim is that a resume makes the uninterrupted run's choices, which any reference shows, and its 8 verify poses
    make each forecast cheaper than the default plan's 24 (both stop after 17 rows)."""
    args = ["--resume", run_id] if run_id else ["--sim", "--adaptive", "--sim-config", str(tmp / "sim.toml"),
                                                "--station", str(tmp / "station.toml"), "--station-timing", "--plan",
                                                str(tmp / "plan.json")]
    env = {**os.environ, "HILCAL_RECORDS": str(tmp / f"{out.name}.sqlite")}
    return subprocess.Popen([sys.executable, "-m", "procedures.cli", "run", "--yes", "--operator", "T", "--out",
                             str(out), *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)


def _kill_when(proc: subprocess.Popen[bytes], journal: Path, done, delay_s: float = 0.0) -> None:
    """SIGKILL the runner once done(journal state) holds (then after delay_s), or let it end by itself."""
    while proc.poll() is None:
        if done(*_journal(journal)):
            time.sleep(delay_s)
            proc.send_signal(signal.SIGKILL)
            break
        time.sleep(0.02)
    proc.wait(30)
    time.sleep(0.3)  # the simulator notices its parent is gone


def test_sigkill_mid_adaptive_then_resume_makes_the_same_choices(tmp_path: Path, calibration_plan: Path) -> None:
    shutil.copy(calibration_plan, tmp_path / "plan.json")
    (tmp_path / "sim.toml").write_text(INSTANT_SIM)
    (tmp_path / "station.toml").write_text(instant_timing())
    rng = np.random.default_rng(28)
    # in the repeats, while the parameters are not yet identifiable, and once predictions decide
    kill_at = [int(rng.integers(1, 4)), int(rng.integers(5, 10)), int(rng.integers(11, 16))]
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    reference = _start(tmp_path, whole, None)
    run_id, counts = None, []
    for k in kill_at:
        proc = _start(tmp_path, killed, run_id)
        _kill_when(proc, killed / "journal.sqlite", lambda rows, stop, rid, k=k: len(rows) >= k or stop,
                   float(rng.uniform(0.0, 0.2)))
        rows, stop, run_id = _journal(killed / "journal.sqlite")
        assert stop is None, f"the measure phase ended before the kill at {k} rows: move the kill points"
        counts.append(len(rows))
    assert counts == sorted(counts) and counts[0] >= 1, counts
    _kill_when(_start(tmp_path, killed, run_id), killed / "journal.sqlite", lambda rows, stop, rid: stop)
    _kill_when(reference, whole / "journal.sqlite", lambda rows, stop, rid: stop)
    poses, stop, _ = _journal(killed / "journal.sqlite")
    expected, expected_stop, _ = _journal(whole / "journal.sqlite")
    assert stop is not None and expected_stop is not None
    assert np.array_equal(poses, expected), "the resumed run chose other poses than the uninterrupted one"
    assert (stop["stop"]["kind"], stop["n_rows"]) == (expected_stop["stop"]["kind"], expected_stop["n_rows"])

    # the same choices by construction: the journal's rows, replayed in a fresh process's problem, choose each pose
    from hilcal.planning.sequential import decide, replay
    from hilcal.robot import default_robot
    from procedures.adaptive import AdaptiveOptions, adaptive_run
    from procedures.plan import CalibrationPlan
    from procedures.timing import TimingSection

    db = sqlite3.connect(killed / "journal.sqlite")
    plan_json, options = db.execute("SELECT plan_json, options_json FROM run").fetchone()
    rows = db.execute("SELECT cmd_json, legs_json, meas_json FROM measurements WHERE phase = 'measure' ORDER BY seq"
                      ).fetchall()
    options = json.loads(options)
    run = adaptive_run(CalibrationPlan.model_validate_json(plan_json), default_robot(),
                       TimingSection.model_validate(options["timing"]).timing(),
                       AdaptiveOptions.model_validate(options["adaptive"]))
    measured = [tuple(np.array(json.loads(c)) for c in row) for row in rows]
    for k in sorted({*counts, len(measured) - 1}):
        assert np.array_equal(decide(run.problem, replay(run.problem, measured[:k])).next.pose, measured[k][0])
