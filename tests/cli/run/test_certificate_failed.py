"""The sign-off of a run that cannot be accepted: a servo with 0.02 mm repeatability per leg, 30 ISO 9283 cycles and
an RP limit it cannot meet (exit code 4, the failing limit named, the records' verdict), and the repeatability
measured back. The expected RP comes from a Monte Carlo through the nominal kinematics written here, not from hilcal.
"""

from __future__ import annotations

import json
import sqlite3
import subprocess
from pathlib import Path

import numpy as np
import pytest

from hilcal.kinematics import Geometry, forward_kinematics, inverse_kinematics
from hilcal.robot import Robot, default_robot
from tests.cli.run.certificate_support import OPERATOR, REPEATABILITY_MM, STATION, hilcal, pdf_text
from tests.cli.sim_speed import INSTANT_SIM

pytestmark = [pytest.mark.slow, pytest.mark.timeout(420)]


@pytest.fixture(scope="module")
def failed(tmp_path_factory: pytest.TempPathFactory, small_plan: Path) -> tuple[Path, subprocess.CompletedProcess]:
    """A servo with 0.02 mm repeatability per leg, 30 cycles, and an RP limit it cannot meet."""
    tmp = tmp_path_factory.mktemp("failed")
    (tmp / "station.toml").write_text(STATION)
    (tmp / "sim.toml").write_text(INSTANT_SIM.replace("[controller]\n", f"[controller]\nrepeatability_mm = "
                                                      f"{REPEATABILITY_MM}\nrepeatability_seed = 7\n"))
    done = hilcal("run", "--sim", "--yes", "--operator", OPERATOR, "--acceptance", "iso9283",
                   "--station", str(tmp / "station.toml"), "--station-timing", "--sim-config", str(tmp / "sim.toml"),
                   "--plan", str(small_plan), "--out", str(tmp / "run"), records=tmp / "records.sqlite")
    return tmp, done


def test_limits_the_machine_cannot_meet_fail_with_exit_code_4(failed: tuple[Path, subprocess.CompletedProcess]
                                                              ) -> None:
    tmp, done = failed
    assert done.returncode == 4, done.stdout + done.stderr
    output = done.stdout + done.stderr
    assert "NOT ACCEPTED" in output and "ISO 9283 position repeatability RP_l at every test pose fail" in output
    report = json.loads((tmp / "run" / "report.json").read_text())
    cert = report["certificate"]
    decisions = {c["key"]: c["decision"] for c in cert["limits"]}
    assert cert["verdict"] == "fail"
    assert decisions == {"max_position_mm": "pass", "ap_position_mm": "pass", "rp_position_mm": "fail"}
    failing = next(c for c in cert["limits"] if c["key"] == "rp_position_mm")
    assert failing["value"] - failing["U"] > failing["limit"] == 0.02
    assert report["machine"]["serial"] == "SIM-0001" and report["station"]["name"] == "test bay"
    assert report["instrument"]["overdue"] is True and "overdue" in " ".join(cert["warnings"])
    assert report["instrument"]["stated_uncertainty_mm"] == 0.002 and report["uncertainty"]["cmm_pose_sd"]
    pdf = pdf_text(tmp / "run" / "certificate.pdf")
    assert "Verdict: fail" in pdf and "ISO 9283 position repeatability RP_l" in pdf and "OVERDUE" in pdf
    db = sqlite3.connect(tmp / "records.sqlite")
    try:
        assert db.execute("SELECT verdict, station, machine_serial FROM runs").fetchone() == (
            "fail", "test bay", "SIM-0001")
    finally:
        db.close()


def _expected_rp(robot: Robot, commanded: np.ndarray, sigma_mm: float, cycles: int, rng: np.random.Generator,
                 experiments: int = 400) -> float:
    """E[l̄ + 3 S_l] over experiments of `cycles` visits, each leg off by N(0, sigma²), nominal kinematics."""
    geom = Geometry.nominal(robot)
    legs = inverse_kinematics(geom, commanded)
    errors = rng.normal(0.0, sigma_mm, (experiments * cycles, 6))
    poses = forward_kinematics(geom, legs + errors, commanded).reshape(experiments, cycles, 6)
    centre = poses[..., :3].mean(axis=1, keepdims=True)
    lengths = np.sqrt(((poses[..., :3] - centre) ** 2).sum(axis=-1))
    return float(np.mean(lengths.mean(axis=1) + 3.0 * lengths.std(axis=1, ddof=1)))


def test_the_simulated_repeatability_is_measured_back(failed: tuple[Path, subprocess.CompletedProcess]) -> None:
    tmp, done = failed
    assert done.returncode == 4, done.stdout + done.stderr
    iso = json.loads((tmp / "run" / "report.json").read_text())["iso9283"]
    assert iso["cycles"] == 30 and all(p["n_cycles"] == 30 for p in iso["poses"])
    robot = default_robot()
    rng = np.random.default_rng(11)
    expected = [_expected_rp(robot, np.array(p["commanded"]), REPEATABILITY_MM, 30, rng) for p in iso["poses"]]
    measured = [p["rp_l_mm"]["value"] for p in iso["poses"]]
    assert np.mean(measured) == pytest.approx(np.mean(expected), rel=0.10)
    assert all(0.7 < m / e < 1.3 for m, e in zip(measured, expected, strict=True))


