"""A machine with gross set-up faults is measured by the run, safely (issue 33): a transducer gradient 4 % wrong with
joints and leg offsets N(0, 3 mm) (three times the paper's) and leg compliance completes with the probe never crossing
a sphere, and the diagnosis of its own recording names the fault; a dead transducer stops the run with the leg named
before a second pose is measured. The simulated CMM stops on any positioning move through a sphere and logs it.

The runs measure tests/cli/conftest.py's calibration plan (the default measurement design, 8 verify poses): the
claims are the measure phase's searches, the diagnosis and a bound of 10 µm on the verification after the upload."""

from __future__ import annotations

import json
import sqlite3
import subprocess
from pathlib import Path

import numpy as np
import pytest

from tests.cli.in_process import hilcal_in_process
from tests.cli.sim_speed import INSTANT_SIM


def _errors_file(path: Path, sd_mm: float, seed: int) -> Path:
    rng = np.random.default_rng(seed)
    legs = [f"[[legs]]\nda_mm = {rng.normal(0, sd_mm, 3).tolist()}\ndb_mm = {rng.normal(0, sd_mm, 3).tolist()}\n"
            f"dl0_mm = {float(rng.normal(0, sd_mm))}\n" for _ in range(6)]
    path.write_text("\n".join(legs))
    return path


def _run(tmp_path: Path, config: str, plan: Path, controller: str = "") -> tuple[subprocess.CompletedProcess, Path]:
    """The run on the near-instant simulator with `config` added, `controller` keys in its [controller] table and a
    CMM that stops on any crash."""
    sim = INSTANT_SIM.replace("[controller]\n", f"[controller]\n{controller}").replace(
        "[cmm]\n", '[cmm]\non_collision = "stop"\n')
    (tmp_path / "sim.toml").write_text(sim + config)
    out = tmp_path / "run"
    env = {"HILCAL_RECORDS": str(tmp_path / "records.sqlite"), "COLUMNS": "200"}
    done = hilcal_in_process("run", "--sim", "--yes", "--plan", str(plan), "--sim-config", str(tmp_path / "sim.toml"),
                             "--out", str(out), env=env)
    return done, out


def _details(out: Path) -> list[dict]:
    with sqlite3.connect(out / "journal.sqlite") as db:
        return [json.loads(d) for (d,) in db.execute("select detail_json from measurements order by seq")]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_4_percent_gradient_with_3_mm_assembly_errors_is_measured_without_a_collision(tmp_path, calibration_plan):
    errors = _errors_file(tmp_path / "errors.toml", 3.0, seed=1)
    done, out = _run(tmp_path, f"""[rig]
errors = "{errors}"
[rig.effects.sensor_scale]
enabled = true
gain_error_ppm = [0.0, 0.0, 0.0, 40000.0, 0.0, 0.0]
[rig.effects.leg_compliance]
enabled = true
""", calibration_plan)
    assert done.returncode == 0, done.stdout + done.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "complete"
    assert "cmm_sim.collision" not in (out / "sim.log").read_text()
    details = _details(out)
    assert details[0]["searched_spheres"] >= 3, "the first pose is predicted only to the robot file's tolerances"
    assert sum(d["searched_spheres"] for d in details[5:]) == 0, "after a few poses the predictions are sub-mm"
    scale = [f for f in report["physics"]["findings"] if "transducer scale" in f]
    assert scale and "Leg 4 reads 4.0" in scale[0], report["physics"]["findings"]
    assert report["verification"]["after"]["rms_position_mm"] < 0.01


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_a_dead_transducer_stops_the_run_naming_the_leg_at_the_first_move(tmp_path, calibration_plan):
    done, out = _run(tmp_path, "", calibration_plan, controller="dead_transducer_legs = [4]\n")
    assert done.returncode == 3, done.stdout + done.stderr
    assert "leg 4 read" in done.stdout + done.stderr and "does not follow the leg" in done.stdout + done.stderr
    assert len(_details(out)) <= 1
