"""Link drop-outs in full `hilcal run --sim` runs: short heartbeat gaps are ridden through, a long one ends the
run cleanly, nothing is commanded once the host can know the link is down, and the printed resume command
works when pasted. The gaps are made by the simulated controller (it sends no frame while one lasts)."""

from __future__ import annotations

import json
import os
import shlex
import sqlite3
import subprocess
import sys
from pathlib import Path

import cantools
import pytest

import hilcal.protocols
from tests.cli.sim_speed import INSTANT_SIM

DBC = cantools.database.load_file(str(Path(hilcal.protocols.__file__).with_name("controller.dbc")))
HOST_FRAMES = {msg.frame_id: msg.name for msg in DBC.messages if "HOST" in msg.senders}
LATE_S = 0.1
"""The station's heartbeat_timeout_s (default): after this silence the host must send nothing but an e-stop."""
MARGIN_S = 0.1
"""Frames already on their way when the host noticed (pty buffers, a busy computer)."""


def _run(args: list[str], tmp: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "HILCAL_RECORDS": str(tmp / "records.sqlite")}
    return subprocess.run([sys.executable, "-m", "procedures.cli", "run", "--yes", *args], capture_output=True,
                          text=True, env=env, timeout=600, check=False)


def _config(tmp: Path, **gaps: object) -> Path:
    """Gaps at counts of frames the controller received (commands, not seconds); the servo and the CMM work at once
    (tests/cli/sim_speed.py), so the run is not spent waiting for simulated motion and probing."""
    lines = ["[controller.can_faults]", f'gap_log = "{tmp / "gaps.jsonl"}"']
    lines += [f"{key} = {json.dumps(value)}" for key, value in gaps.items()]
    path = tmp / "sim.toml"
    path.write_text(INSTANT_SIM + "\n".join(lines) + "\n")
    return path


def _gap_log(tmp: Path) -> tuple[list[dict], list[dict]]:
    records = [json.loads(line) for line in (tmp / "gaps.jsonl").read_text().splitlines()]
    return [r for r in records if r["event"] == "gap"], [r for r in records if r["event"] == "received_in_gap"]


def _late_commands(received: list[dict]) -> list[dict]:
    """Frames other than an e-stop that reached the controller after the host should have seen the gap."""
    return [r for r in received if HOST_FRAMES.get(r["frame_id"]) != "EstopRequest"
            and r["into_gap_s"] > LATE_S + MARGIN_S]


def _journal(folder: Path, sql: str) -> list[tuple]:
    db = sqlite3.connect(f"file:{folder / 'journal.sqlite'}?mode=ro", uri=True)
    try:
        return db.execute(sql).fetchall()
    finally:
        db.close()


@pytest.mark.timeout(900)
def test_short_gaps_are_ridden_through(tmp_path, instant_plan):
    out = tmp_path / "run"
    config = _config(tmp_path, gap_at_frames=[40, 250, 500, 800, 1100, 1400], gap_min_s=0.2, gap_max_s=0.6,
                     seed=5)
    done = _run(["--sim", "--sim-config", str(config), "--plan", str(instant_plan), "--out", str(out)], tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    gaps, received = _gap_log(tmp_path)
    assert len(gaps) == 6 and all(0.2 <= g["length_s"] <= 0.6 for g in gaps)
    assert not _late_commands(received), _late_commands(received)
    holds = _journal(out, "SELECT data_json FROM events WHERE kind = 'link_hold'")
    assert len(holds) >= 3, "gaps longer than the heartbeat timeout during motion must hold the run"
    report = json.loads((out / "report.json").read_text())
    controller = report["links"]["controller"]
    assert controller["holds"] == len(holds) and not controller["lost"]
    assert 0 < controller["longest_hold_s"] < 0.6, "a hold ends when the heartbeats return"
    assert "controller: " in done.stdout and "holds/retries" in done.stdout
    rows = _journal(out, "SELECT phase, pose_index FROM measurements")
    assert len(rows) == len(set(rows)) == 35 + 24 + 24, "every pose measured exactly once"
    assert report["verification"]["after"]["max_position_mm"] <= 0.05


@pytest.mark.timeout(900)
def test_a_long_gap_ends_the_run_and_the_printed_command_resumes_it(tmp_path, instant_plan):
    out = tmp_path / "run folder with spaces"
    config = _config(tmp_path, gap_at_frames=[300], gap_min_s=1.6, gap_max_s=1.8, max_gaps=1)
    stopped = _run(["--sim", "--sim-config", str(config), "--plan", str(instant_plan), "--out", str(out)], tmp_path)
    assert stopped.returncode == 3, stopped.stdout + stopped.stderr
    assert "controller link lost" in stopped.stderr and "grace period" in stopped.stderr
    gaps, received = _gap_log(tmp_path)
    assert len(gaps) == 1 and not _late_commands(received), received
    assert _journal(out, "SELECT COUNT(*) FROM events WHERE kind = 'link_lost'") == [(1,)]
    measured = _journal(out, "SELECT COUNT(*) FROM measurements")[0][0]
    assert 0 < measured < 35

    command = stopped.stderr.split("continue with: ", 1)[1].strip().splitlines()[0]
    argv = shlex.split(command)
    assert argv[:3] == ["hilcal", "run", "--resume"] and argv[argv.index("--out") + 1] == str(out)
    resumed = _run(argv[2:], tmp_path)
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    rows = _journal(out, "SELECT phase, pose_index FROM measurements")
    assert len(rows) == len(set(rows)) == 35 + 24 + 24
    assert _gap_log(tmp_path)[0] == gaps, "max_gaps counts across the simulator's restart"
