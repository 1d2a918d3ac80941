"""A newcomer's first hour, from the README alone: its geometry file, `hilcal robot-from-geometry`, `hilcal run --sim
--yes --robot robot.toml` (the simulator runs that robot, with the default errors on it, and says so), the report and
the certificate in words, then `hilcal sim --station-out` and `hilcal check` on the simulated station.

The commands and the geometry file are read from the README's "Describing your machine" and "Your machine, in
simulation"; only the instant simulator and a small plan are added to the run, for speed (tests/cli/sim_speed.py).
"""

from __future__ import annotations

import html
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from typer.testing import CliRunner

from hilcal.robot import load_robot
from procedures.cli.app import app
from procedures.cli.sim_station import SIM_TIMING
from procedures.plan import make_plan, save_plan
from tests.cli.in_process import hilcal_in_process
from tests.cli.sim_speed import DEVICES_INSTANT, INSTANT_SIM

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text()
SNAKE_KEY = re.compile(r"\b[a-z][a-z0-9]*(?:_[a-z0-9]+)+\b")
"""A key of report.json or a station file as it is spelled there (max_position_mm, predicted_basis)."""


def _section(title: str) -> str:
    return re.split(r"\n##+ ", README.split(f"### {title}\n", 1)[1], maxsplit=1)[0]


def _blocks(text: str, kind: str) -> list[str]:
    return re.findall(rf"```{kind}\n(.*?)```", text, re.S)


def _commands(block: str) -> list[list[str]]:
    return [shlex.split(line.split(" #")[0])[1:] for line in block.splitlines() if line.startswith("hilcal ")]


def visible_text(page: str) -> str:
    """What a browser shows of an HTML page: no style, no images, no tags."""
    page = re.sub(r"<style>.*?</style>", " ", page, flags=re.S)
    page = re.sub(r"<img[^>]*>", " ", page)
    return " ".join(html.unescape(re.sub(r"<[^>]+>", " ", page)).split())


def _env(work: Path) -> dict[str, str]:
    return {**os.environ, "HILCAL_RECORDS": str(work / "records.sqlite"), "COLUMNS": "200",
            "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}


@pytest.fixture(scope="module")
def newcomer(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The README's geometry file and commands, in an empty folder."""
    work = tmp_path_factory.mktemp("newcomer")
    (work / "geometry.toml").write_text(_blocks(_section("Describing your machine"), "toml")[0])
    to_robot, to_run = _commands(_blocks(_section("Your machine, in simulation"), "sh")[0])
    made = hilcal_in_process(*to_robot, cwd=work, env=_env(work))
    plan = work / "small_plan.json"
    if made.returncode == 0:  # a small plan for the newcomer's robot, without the settle wait
        save_plan(make_plan(load_robot(work / "robot.toml"), 0, n_measure=12, n_verify=6, settle_s=0.0,
                            timing=SIM_TIMING.timing()), plan)
    (work / "instant.toml").write_text(INSTANT_SIM)
    ran = hilcal_in_process(*to_run, "--sim-config", str(work / "instant.toml"), "--plan", str(plan), cwd=work,
                            env=_env(work))
    folders = sorted((work / "runs").glob("*")) if (work / "runs").is_dir() else []
    return {"work": work, "made": made, "ran": ran, "run": folders[0] if folders else None,
            "commands": (to_robot, to_run)}


def test_the_readme_gives_the_newcomers_commands(newcomer: dict) -> None:
    to_robot, to_run = newcomer["commands"]
    assert to_robot == ["robot-from-geometry", "geometry.toml", "--out", "robot.toml"]
    assert to_run == ["run", "--sim", "--yes", "--robot", "robot.toml"]


def test_the_geometry_file_becomes_a_robot_file_with_stated_defaults(newcomer: dict) -> None:
    made = newcomer["made"]
    assert made.returncode == 0, made.stdout + made.stderr
    said = " ".join(made.stdout.split())
    assert "default travel: not in the geometry file" in said and "default mass: not in the geometry file" in said
    robot = load_robot(newcomer["work"] / "robot.toml")
    assert robot.name == "my-hexapod" and robot.spec.mass is not None


def test_the_simulator_runs_the_newcomers_robot_and_says_so(newcomer: dict) -> None:
    ran, run = newcomer["ran"], newcomer["run"]
    assert ran.returncode == 0, ran.stdout + ran.stderr
    said = " ".join(ran.stdout.split())
    assert "refuse" not in said and "not the same robot" not in said
    assert f"simulated machine: robot my-hexapod ({newcomer['work'] / 'robot.toml'})" in said
    assert ("geometric errors: the paper's Table 2 (Yu 2022, in mm for its 3.7 m robot), not scaled to this robot"
            in said)
    report = json.loads((run / "report.json").read_text())
    assert report["status"] == "complete" and report["robot"]["name"] == "my-hexapod"
    assert report["simulation"]["robot"] == {"name": "my-hexapod", "file": str(newcomer["work"] / "robot.toml")}
    plan = json.loads((run / "plan.json").read_text())
    assert plan["robot_name"] == "my-hexapod"
    assert report["verification"]["after"]["max_position_mm"] < 0.05 < report["verification"]["before"][
        "max_position_mm"]  # calibrated: the errors on this robot were found and corrected


def test_the_report_and_the_certificate_speak_in_words(newcomer: dict) -> None:
    run = newcomer["run"]
    report_page = visible_text((run / "report.html").read_text())
    certificate_page = visible_text((run / "certificate.html").read_text())
    for page in (report_page, certificate_page):
        keys = sorted({k for k in SNAKE_KEY.findall(page) if not re.search(rf"{k}\.(json|toml|html|pdf)", page)})
        assert keys == [], keys
        assert "tests/" not in page and "[cmm]" not in page
    assert "The simulated machine" in report_page and "my-hexapod" in report_page
    assert "Plausible : the identified corrections are within these bounds" in report_page
    assert "each joint within 10 mm of its nominal position" in report_page
    assert "leg 1: platform joint position, x (mm)" in report_page
    assert "largest position error" in report_page and "mm →" in report_page
    assert "as the simulated CMM states it: twice the standard deviation of one touch point's noise" in (
        certificate_page)
    assert "of the simulated machine's time" in certificate_page


def test_hilcal_check_on_the_simulated_station(newcomer: dict, monkeypatch: pytest.MonkeyPatch) -> None:
    work = newcomer["work"]
    blocks = _blocks(_section("Your machine, in simulation"), "sh")
    sim_args, check_args = _commands(blocks[1])
    assert sim_args[:3] == ["sim", "--robot", "robot.toml"] and check_args[0] == "check"
    (work / "devices.toml").write_text(DEVICES_INSTANT)
    sim = subprocess.Popen([sys.executable, "-m", "procedures.cli", *sim_args, "--config", str(work / "devices.toml")],
                           cwd=work, env=_env(work), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        station = work / sim_args[sim_args.index("--station-out") + 1]
        deadline = time.monotonic() + 60
        while not station.is_file() and sim.poll() is None and time.monotonic() < deadline:
            time.sleep(0.1)
        assert station.is_file(), "the simulator wrote no station file"
        monkeypatch.chdir(work)
        done = CliRunner().invoke(app, check_args)
        assert done.exit_code == 0, done.output
        result = json.loads(done.stdout)
        assert result["ok"] and [d["kind"] for d in result["devices"]] == ["controller", "cmm"]
        assert len(result["devices"][1]["spheres"]) == 3
    finally:
        sim.send_signal(signal.SIGTERM)
        output = sim.communicate(timeout=30)[0]
    assert "simulated machine: robot my-hexapod" in output
