"""A small electric hexapod whose leg 2 transducer reads 0.2 % long: once the run corrects it, a verification pose
near the top of leg 2's 40 mm stroke needs more raw stroke than the leg has. The run must say so before the upload,
leave that pose out of the verification after it and complete, instead of commanding a setpoint the controller
refuses (the run would stop there, and a resume would stop there again)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from tests.cli.in_process import hilcal_in_process
from tests.cli.sim_speed import INSTANT_SIM

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[3]
SMALL = ROOT / "examples" / "hexapod_small.toml"


@pytest.mark.timeout(300)
def test_a_pose_the_corrected_machine_cannot_reach_is_left_out_and_said(tmp_path):
    (tmp_path / "sim.toml").write_text(f'robot = "{SMALL}"\n' + INSTANT_SIM + """
[rig]
errors = "zero"
[rig.effects.sensor_scale]
enabled = true
gain_error_ppm = [0.0, 2000.0, 0.0, 0.0, -1500.0, 0.0]
""")
    out = tmp_path / "run"
    env = {"HILCAL_RECORDS": str(tmp_path / "records.sqlite"), "COLUMNS": "200"}
    done = hilcal_in_process("run", "--sim", "--yes", "--robot", str(SMALL), "--sim-config", str(tmp_path / "sim.toml"),
                             "--out", str(out), env=env)
    assert done.returncode == 0, done.stdout + done.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["status"] == "complete" and report["compensation"]["compensation_block"] is not None
    [warning] = report["warnings"]
    match = re.match(r"verify pose (\d+) is beyond leg 2's travel with the new parameters: it needs a raw stroke of "
                     r"40\.0\d\d mm, above its 40\.000 mm: it is not measured after the upload", warning)
    assert match, warning
    after = report["per_pose"]["after"]["position_mm"]
    assert [k for k, v in enumerate(after) if v is None] == [int(match.group(1)) - 1]
    assert len(after) == len(report["per_pose"]["before"]["position_mm"]) == 24
    assert report["verification"]["after"]["max_position_mm"] < 0.2 * report["verification"]["before"][
        "max_position_mm"]
    assert "setpoint_refused" not in (out / "sim.log").read_text()  # nothing was commanded beyond the stroke
    end = " ".join(done.stdout[done.stdout.index(f"run {report['run_id']}: complete"):].split())
    assert "after (23 poses)" in end and f"warning {warning}" in end
