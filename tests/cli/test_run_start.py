"""How a run starts and why it stops, in words: a station whose device does not answer is not a stopped run (it names
the device and its setting, exits 3 without a resume hint and leaves no run behind); an abort at a question says
which question and why (the operator's no, or standard input closed); a simulated run's certificate states its
temperatures over the simulated machine's time, which its clock runs faster than the wall clock."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from procedures.certificate import _environment
from procedures.cli.app import app
from tests.cli.sim_speed import INSTANT_SIM

ROOT = Path(__file__).resolve().parents[2]
STATION = """name = "bay 2"
[can]
interface = "socketcan"
channel = "hilcalnone0"
[modbus]
host = "127.0.0.1"
[cmm]
url = "loop://"
alignment = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
"""
"""A station whose CAN interface does not exist (socketcan needs a kernel interface of that name)."""


def test_a_station_that_cannot_connect_is_not_a_stopped_run(tmp_path: Path, small_plan: Path,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    (tmp_path / "station.toml").write_text(STATION)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["run", "--station", "station.toml", "--yes", "--operator", "T", "--plan",
                                      str(small_plan), "--records", str(tmp_path / "records.sqlite")],
                                env={"COLUMNS": "200"})
    said = " ".join(result.output.split())
    assert result.exit_code == 3, result.output
    assert "the run did not start: cannot connect to the controller's CAN interface socketcan, channel hilcalnone0: " \
           in said
    assert "{'" not in said and "resume" not in said and said.count("hilcalnone0") == 1
    assert "Nothing moved and no run was recorded" in said
    assert list((tmp_path / "runs").iterdir()) == []  # the run folder it announced is gone: nothing to resume

    kept = tmp_path / "mine"
    kept.mkdir()
    (kept / "notes.txt").write_text("the operator's")
    again = CliRunner().invoke(app, ["run", "--station", "station.toml", "--yes", "--operator", "T", "--plan",
                                     str(small_plan), "--out", str(kept), "--records",
                                     str(tmp_path / "records.sqlite")])
    assert again.exit_code == 3 and sorted(p.name for p in kept.iterdir()) == ["notes.txt"]  # only what it wrote goes


def _run(work: Path, plan: Path, answers: str | None) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "HILCAL_RECORDS": str(work / "records.sqlite"), "COLUMNS": "200",
           "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    (work / "instant.toml").write_text(INSTANT_SIM)
    return subprocess.run([sys.executable, "-m", "procedures.cli", "run", "--sim", "--operator", "T", "--sim-config",
                           str(work / "instant.toml"), "--plan", str(plan), "--out", str(work / "run")],
                          input=answers, stdin=subprocess.DEVNULL if answers is None else None, env=env, cwd=work,
                          capture_output=True, text=True, timeout=120, check=False)


@pytest.mark.slow
def test_an_abort_says_at_which_question_and_why(tmp_path: Path, small_plan: Path) -> None:
    for name in ("closed", "no"):
        (tmp_path / name).mkdir()
    closed = _run(tmp_path / "closed", small_plan, None)
    said = " ".join((closed.stdout + closed.stderr).split())
    assert closed.returncode == 3, said
    question = re.search(r"stopped: standard input closed while asking '([^']+)'", said)
    assert question is not None and question.group(1) in said.split("stopped:")[0], said  # the question it asked
    assert "Abort" not in said and "continue with: hilcal run --resume" in said  # a started run is resumable

    declined = _run(tmp_path / "no", small_plan, "n\n")
    said = " ".join((declined.stdout + declined.stderr).split())
    assert declined.returncode == 3, said
    assert re.search(r"stopped: the operator answered no to the question '[^']+'", said), said


def test_a_simulated_runs_temperatures_are_stated_over_the_simulated_machines_time() -> None:
    """The 4-minute simulated run of the issue: 10 K over 229 s of wall clock is 6.4 h of a clock 100 times faster."""
    rows = [{"seq": k, "time_s": 229.0 * k / 99, "detail": {"temp_c": 21.03 + 10.2 * k / 99}} for k in range(100)]
    env = _environment(rows, {"time_scale": 100.0})
    assert env["measurements_span_s"] == pytest.approx(229.0) and env["machine_span_s"] == pytest.approx(22900.0)
    assert env["note"] == ("the simulated controller's temperature readings, over 6.4 h of the simulated machine's "
                           "time (its clock runs 100 times faster than real time: 3.8 min here)")
    assert env["temperature_c"]["max"] - env["temperature_c"]["min"] == pytest.approx(10.2)
    resumed = [*rows[:50], *({**r, "seq": r["seq"] + 100, "time_s": r["time_s"] - rows[50]["time_s"] + 3.0}
                             for r in rows[50:])]  # a second session's engine clock starts again near zero
    gap = rows[50]["time_s"] - rows[49]["time_s"]  # between the sessions: not measuring time
    assert _environment(resumed, {"time_scale": 100.0})["measurements_span_s"] == pytest.approx(229.0 - gap)
    real = _environment(rows, None)
    assert real["machine_span_s"] == pytest.approx(229.0) and "simulated" not in real["note"]


def test_a_resume_looks_in_runs_by_default(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["run", "--resume", "20260101T000000Z-abcdef"], env={"COLUMNS": "200"})
    said = " ".join(result.output.split())
    assert result.exit_code == 2, said
    assert ("cannot resume 20260101T000000Z-abcdef: runs/20260101T000000Z-abcdef holds no run journal "
            "(journal.sqlite); give --out with the run's folder") in said
    assert not (tmp_path / "runs").exists()  # looking made nothing
