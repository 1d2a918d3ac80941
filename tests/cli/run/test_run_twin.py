"""The digital twin runs (issue 33): a recording of the 320 mm-stroke hexapod whose leg 3 reads 4 % long is
diagnosed with `--report`; `hilcal run --sim --sim-config REPORT/sim_config.toml` with no `--robot` measures the
twin's machine (its robot, from the report) without a collision, and its own recording, diagnosed again, names the
same first effect on the same leg within 10 %."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest

from tests.cli.in_process import hilcal_in_process
from tests.cli.sim_speed import DEVICES_INSTANT

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[3]
ROBOT = ROOT / "examples" / "hexapod_stroke320.toml"


def _hilcal(*args: str, env: dict) -> subprocess.CompletedProcess:
    return hilcal_in_process(*args, env=env)


def _first_effect(diagnosis: dict) -> tuple[str, int, float]:
    effect = diagnosis["steps"][0]["effect"]
    legs = [p for p in diagnosis["parameter_table"] if p["effect"] == effect]
    top = max(legs, key=lambda p: abs(p["value"]))
    return effect, top["leg"], top["value"]


@pytest.mark.timeout(300)
def test_the_twin_of_a_4_percent_fault_runs_and_shows_the_same_fault(tmp_path):
    env = {"HILCAL_RECORDS": str(tmp_path / "records.sqlite"), "COLUMNS": "200"}
    (tmp_path / "rig.toml").write_text(f'robot = "{ROBOT}"\n[rig]\nseed = 2\n[rig.effects.sensor_scale]\n'
                                       "enabled = true\ngain_error_ppm = [0.0, 0.0, 40000.0, 0.0, 0.0, 0.0]\n")
    done = _hilcal("simulate", "--out", str(tmp_path / "rec.csv"), "--sim-config", str(tmp_path / "rig.toml"),
                   "--seed", "2", env=env)
    assert done.returncode == 0, done.stderr
    report = tmp_path / "report"
    done = _hilcal("diagnose", str(tmp_path / "rec.csv"), "--robot", str(ROBOT), "--report", str(report), "--json",
                   env=env)
    assert done.returncode == 0, done.stderr
    original = _first_effect(json.loads(done.stdout))
    assert original[:2] == ("sensor_scale", 3)
    # the twin as written, with the near-instant servo and a CMM that stops on any crash (same folder: its paths hold)
    twin = report / "twin_instant.toml"
    twin.write_text((report / "sim_config.toml").read_text() + DEVICES_INSTANT.replace(
        "[cmm]\n", '[cmm]\non_collision = "stop"\n'))
    out = tmp_path / "run"
    done = _hilcal("run", "--sim", "--yes", "--sim-config", str(twin), "--out", str(out), env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "cmm_sim.collision" not in (out / "sim.log").read_text()
    plan = json.loads((out / "plan.json").read_text())
    assert plan["robot_name"] == "electric-hexapod-stroke320"  # the twin's robot, not the built-in one
    done = _hilcal("diagnose", str(out / "recording.csv"), "--robot", str(report / "robot.toml"), "--json", env=env)
    assert done.returncode == 0, done.stderr
    again = _first_effect(json.loads(done.stdout))
    assert again[:2] == original[:2]
    assert again[2] == pytest.approx(original[2], rel=0.10)
