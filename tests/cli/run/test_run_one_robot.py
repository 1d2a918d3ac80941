"""One robot per run: `hilcal run` plans, moves and measures with the robot of the simulator's configuration when
only that names one (a digital twin's `sim_config.toml`), keeps it on resume, and refuses before anything starts a
--robot or a station file's robot that is not the machine's, naming both files, the first difference and the fix.
(A simulator config that names no robot simulates the run's: tests/cli/test_newcomer.py.)"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from procedures.cli.app import app
from procedures.journal import Journal
from tests.cli.in_process import hilcal_in_process
from tests.cli.sim_speed import INSTANT_SIM

ROOT = Path(__file__).resolve().parents[3]
SMALL = ROOT / "examples" / "hexapod_small.toml"
SMALL_HOME_Z_MM = 100.0
"""examples/hexapod_small.toml's home height; its workspace's z is 88-115 mm (the paper robot's is about 2850)."""
LEG3_A = "a_mm = [-40.15, 57.34, 0.0]"

runner = CliRunner()


def _twin(folder: Path) -> Path:
    """A twin's layout: sim_config.toml naming its robot file beside it, by a relative path."""
    folder.mkdir(parents=True)
    shutil.copyfile(SMALL, folder / "robot.toml")
    (folder / "sim_config.toml").write_text('robot = "robot.toml"\n' + INSTANT_SIM + '[rig]\nerrors = "zero"\n')
    return folder / "sim_config.toml"


def _refused(args: list[str], out: Path) -> str:
    result = runner.invoke(app, ["run", *args, "--out", str(out)])
    assert result.exit_code == 2, result.output
    assert not out.exists(), "refused before anything starts"
    return " ".join(result.output.split())


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_the_simulators_robot_is_the_runs_and_stays_so_on_resume(tmp_path):
    config = _twin(tmp_path / "twin")
    out = tmp_path / "run"
    env = {"HILCAL_RECORDS": str(tmp_path / "records.sqlite"), "COLUMNS": "200"}
    command = ["run", "--out", str(out)]
    declined = hilcal_in_process(*command, "--sim", "--sim-config", str(config), "--operator", "T", input="n\n",
                                 env=env, cwd=tmp_path)
    assert declined.returncode == 3, declined.stdout + declined.stderr  # no at the first question: resumable
    plan = json.loads((out / "plan.json").read_text())
    assert plan["robot_name"] == "small-electric-hexapod"
    heights = np.array([pose[2] for pose in plan["measure_poses"]])
    assert np.all(np.abs(heights - SMALL_HOME_Z_MM) < 20.0), heights
    with Journal(out / "journal.sqlite") as journal:
        run_id = journal.run_info()["run_id"]

    resumed = hilcal_in_process(*command, "--resume", run_id, "--yes", env=env,
                                cwd=ROOT)  # another folder: the robot's path is absolute
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "complete" and report["robot"]["name"] == "small-electric-hexapod"
    assert "robot=small-electric-hexapod" in (out / "sim.log").read_text()
    assert "setpoint_refused" not in (out / "sim.log").read_text()


def test_a_robot_that_is_not_the_simulators_is_refused(tmp_path):
    config = _twin(tmp_path / "twin")
    said = _refused(["--sim", "--sim-config", str(config), "--robot", str(ROOT / "hilcal" / "data" /
                                                                            "paper_table1.toml")], tmp_path / "a")
    assert f"--robot {ROOT / 'hilcal' / 'data' / 'paper_table1.toml'}" in said
    assert f"the robot of the simulator config {config} ({(tmp_path / 'twin' / 'robot.toml').resolve()})" in said
    assert "the robot names differ: 'paper-table1' vs 'small-electric-hexapod'" in said

    moved = tmp_path / "moved.toml"
    moved.write_text(SMALL.read_text().replace(LEG3_A, "a_mm = [-40.15, 57.34, 0.5]"))
    said = _refused(["--sim", "--sim-config", str(config), "--robot", str(moved)], tmp_path / "b")
    assert f"--robot {moved} and the robot of the simulator config {config}" in said
    assert "leg 3's a_mm differs: z 0.5 vs 0.0 mm" in said

    assert "Fix: leave out --robot to run the robot the simulator config" in said  # and how to put it right


def test_a_station_files_robot_that_is_not_the_robots_is_refused(tmp_path):
    moved = tmp_path / "robots" / "bay2.toml"
    moved.parent.mkdir()
    moved.write_text(SMALL.read_text().replace(LEG3_A, "a_mm = [-40.15, 57.34, 0.5]"))
    station = tmp_path / "station.toml"
    station.write_text('robot = "robots/bay2.toml"\n[timing]\nsettle_s = 0.0\n')
    said = _refused(["--station", str(station), "--robot", str(SMALL)], tmp_path / "a")
    assert f"--robot {SMALL} and the robot of the station file {station} ({moved.resolve()})" in said
    assert "leg 3's a_mm differs: z 0.0 vs 0.5 mm" in said

    config = _twin(tmp_path / "twin")  # with --sim the station file's robot must be the simulator's as well
    said = _refused(["--sim", "--sim-config", str(config), "--station", str(station)], tmp_path / "b")
    assert f"the robot of the station file {station}" in said and "leg 3's a_mm differs: z 0.5 vs 0.0 mm" in said

    station.write_text("[timing]\nsettle_s = 0.0\n")  # a real station that names none runs the built-in robot
    said = _refused(["--station", str(station), "--robot", str(SMALL)], tmp_path / "c")
    assert f"the station file {station} (it names no robot: the built-in paper Table 1 robot)" in said
