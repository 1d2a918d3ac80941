"""What the link-gap tests share: the run command, the simulator's gap configuration, its log of gaps and of frames
received in one, and the run's journal."""

from __future__ import annotations

import json
import sqlite3
import subprocess
from pathlib import Path

import cantools

import hilcal.protocols
from tests.cli.in_process import hilcal_in_process
from tests.cli.sim_speed import INSTANT_SIM

DBC = cantools.database.load_file(str(Path(hilcal.protocols.__file__).with_name("controller.dbc")))
HOST_FRAMES = {msg.frame_id: msg.name for msg in DBC.messages if "HOST" in msg.senders}
LATE_S = 0.1
"""The station's heartbeat_timeout_s (default): after this silence the host must send nothing but an e-stop."""
MARGIN_S = 0.1
"""Frames already on their way when the host noticed (pty buffers, a busy computer)."""


def run_hilcal(args: list[str], tmp: Path) -> subprocess.CompletedProcess[str]:
    """`hilcal run --yes ARGS` in this process (tests/cli/in_process.py): the claims are about what the run did in
    its gaps, not about its being a process of its own; its simulator is still a process, over real transports."""
    return hilcal_in_process("run", "--yes", *args, env={"HILCAL_RECORDS": str(tmp / "records.sqlite")})


def sim_config(tmp: Path, **gaps: object) -> Path:
    """Gaps at counts of frames the controller received (commands, not seconds); the servo and the CMM work at once
    (tests/cli/sim_speed.py), so the run is not spent waiting for simulated motion and probing."""
    lines = ["[controller.can_faults]", f'gap_log = "{tmp / "gaps.jsonl"}"']
    lines += [f"{key} = {json.dumps(value)}" for key, value in gaps.items()]
    path = tmp / "sim.toml"
    path.write_text(INSTANT_SIM + "\n".join(lines) + "\n")
    return path


def gap_log(tmp: Path) -> tuple[list[dict], list[dict]]:
    records = [json.loads(line) for line in (tmp / "gaps.jsonl").read_text().splitlines()]
    return [r for r in records if r["event"] == "gap"], [r for r in records if r["event"] == "received_in_gap"]


def late_commands(received: list[dict]) -> list[dict]:
    """Frames other than an e-stop that reached the controller after the host should have seen the gap."""
    return [r for r in received if HOST_FRAMES.get(r["frame_id"]) != "EstopRequest"
            and r["into_gap_s"] > LATE_S + MARGIN_S]


def journal_rows(folder: Path, sql: str) -> list[tuple]:
    db = sqlite3.connect(f"file:{folder / 'journal.sqlite'}?mode=ro", uri=True)
    try:
        return db.execute(sql).fetchall()
    finally:
        db.close()


