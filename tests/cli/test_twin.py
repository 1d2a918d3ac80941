"""The digital twin of `hilcal diagnose --report`: on the electric and paper examples and on study recordings with one
or two effects, the recording replayed on the twin leaves a residual within FACTOR of the noise yardstick, where the
geometry-only twin leaves at least EFFECT_FACTOR of it (the recordings whose effects are that large); the files it
writes are what `hilcal simulate` and `hilcal run --sim` read.

The recordings come from the independent rig (`sim_devices`); the twin is read back from the sim_config.toml it writes,
so the replay runs what a user would load.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from hilcal.discovery.search import diagnose
from hilcal.recording import read_recording
from hilcal.robot import default_robot, load_robot
from procedures.cli.sim_station import SIM_TIMING
from procedures.cli.simulated_recording import simulate_with_truth
from procedures.cli.twin import compare, write_twin
from procedures.plan import make_plan, save_plan
from sim_devices.rig.config import RigConfig
from tests.cli.in_process import hilcal_in_process
from tests.cli.sim_speed import DEVICES_INSTANT

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks" / "studies"))
from diagnosis_cases import _WORKER, Case, effects_config, init_worker  # noqa: E402

FACTOR = 1.2
EFFECT_FACTOR = 5.0
EXAMPLES = ROOT / "examples"


def _twin(rec, robot, robot_path, tmp_path):
    diag = diagnose(rec, robot)
    twin = write_twin(diag, rec, robot, robot_path, tmp_path)
    return diag, twin, compare(twin, diag, rec, robot)


@pytest.mark.slow
def test_the_electric_example_s_twin_holds_the_machine(tmp_path):
    robot_path = EXAMPLES / "electric_hexapod" / "robot.toml"
    robot = load_robot(robot_path)
    _, twin, comparison = _twin(read_recording(EXAMPLES / "electric_hexapod" / "recording.csv", robot), robot,
                                robot_path, tmp_path)
    assert comparison.ratio("physics") <= FACTOR
    assert comparison.ratio("geometry") >= EFFECT_FACTOR
    effects = twin.rig.effects
    assert effects.sensor_scale.enabled and effects.drive_compliance.enabled and effects.leg_tables.enabled
    # Leg 2's mm per revolution is 15/16 of the configured one: the rig reads 1/0.9375 - 1 = 6.67 % long.
    assert effects.sensor_scale.gain_error_ppm[1] == pytest.approx(66_667, rel=0.01)
    assert {t.variable for t in effects.leg_tables.tables} == {"session", "stroke_mm"}


def test_the_paper_example_s_twin_holds_the_machine(tmp_path):
    robot = default_robot()
    diag, twin, comparison = _twin(read_recording(EXAMPLES / "import" / "paper" / "simulated.csv", robot), robot,
                                   None, tmp_path)
    assert diag.effects == ("thermal_expansion",)
    assert twin.rig.effects.thermal_expansion.alpha_ppm_per_k == pytest.approx(diag.parameters[
        "thermal_expansion_ppm_per_K"], rel=0.05)
    assert twin.rig.temperature.table_c is not None
    # Its thermal growth is below EFFECT_FACTOR times the noise: the geometry-only twin is off by less.
    assert comparison.ratio("physics") <= FACTOR < comparison.ratio("geometry")


STUDY = [Case("single", ("thermal_expansion",), 2.0, 0), Case("unlisted", ("transducer_bow",), 1.0, 300),
         Case("unlisted", ("cyclic_stroke_error",), 1.0, 300), Case("unlisted", ("hooke_joint_offset",), 1.0, 300),
         Case("combo", ("transducer_bow", "leg_compliance"), 1.0, 400),
         Case("combo", ("hooke_joint_offset", "leg_compliance"), 1.0, 400)]


@pytest.mark.slow
@pytest.mark.parametrize("case", STUDY, ids=lambda c: "+".join(c.effects))
def test_a_study_recording_s_twin_holds_its_effects(case, tmp_path):
    if "measure" not in _WORKER:  # the study's D-optimal plan, designed once per test process (1.5 s)
        init_worker()
    robot = _WORKER["robot"]
    config = RigConfig(seed=case.seed, errors=_WORKER["table2"], effects=effects_config(case))
    rec, _ = simulate_with_truth(robot, config, _WORKER["measure"], _WORKER["verify"])
    _, _, comparison = _twin(rec, robot, None, tmp_path)
    assert comparison.ratio("geometry") >= EFFECT_FACTOR
    assert comparison.ratio("physics") <= FACTOR


def _hilcal(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return hilcal_in_process(*args, env={"MPLBACKEND": "Agg"}, cwd=cwd)


@pytest.mark.slow
@pytest.mark.timeout(900)
def test_the_twin_is_what_simulate_and_run_sim_read(tmp_path):
    example = EXAMPLES / "small_hexapod"
    robot_path = example / "robot.toml"
    report = tmp_path / "report"
    done = _hilcal("diagnose", str(example / "recording.csv"), "--robot", str(robot_path), "--report", str(report),
                   "--json", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    twin = json.loads(done.stdout)["twin"]
    assert twin["physics"]["times_noise"] <= FACTOR < twin["geometry"]["times_noise"]
    assert (report / "sim_config.toml").exists() and "Digital twin" in (report / "index.html").read_text()
    simulated = _hilcal("simulate", "--sim-config", str(report / "sim_config.toml"), "--out", "twin.csv",
                        cwd=tmp_path)
    assert simulated.returncode == 0, simulated.stderr
    robot = load_robot(robot_path)
    assert diagnose(read_recording(tmp_path / "twin.csv", robot), robot).effect == "joint_backlash"
    paced = report / "twin_instant.toml"  # beside it (its robot file is relative): the devices near-instant
    twin_config = (report / "sim_config.toml").read_text()
    assert "drift_k_per_h = 0.0" in twin_config  # the rig's clock follows the fast servo: a drift would be scaled
    paced.write_text(twin_config + DEVICES_INSTANT)
    plan = tmp_path / "plan.json"  # 6 verify poses: what is checked is that the run reads the twin, not its accuracy
    save_plan(make_plan(robot, 0, n_verify=6, settle_s=0.0, timing=SIM_TIMING.timing()), plan)
    run = _hilcal("run", "--sim", "--yes", "--sim-config", str(paced), "--robot", str(robot_path), "--plan",
                  str(plan), "--out", str(tmp_path / "run"), "--records", str(tmp_path / "records.sqlite"),
                  cwd=tmp_path)
    assert run.returncode == 0, run.stdout + run.stderr
    assert json.loads((tmp_path / "run" / "report.json").read_text())["status"] == "complete"
