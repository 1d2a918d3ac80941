"""Physics to the machine: `hilcal run --sim` on a rig with set-up faults and a compliance it does not know of.

The rig's transducers of legs 1 and 4 read 0.30 % long and 0.20 % short (wrong gradients after a replacement) and
its legs sag 6 µm/kN. The run must diagnose its own recording, upload the geometry fitted with the effects and the
controller's compensation block in one transaction, and the verification after the upload must measure at the
machine what the diagnosis predicted. With --physics off the same rig is refused (the geometric fit absorbs the
faults into joint errors of tens of mm).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hilcal.protocols.compensation import block_from_words
from procedures.records import Records
from tests.cli.in_process import hilcal_in_process
from tests.cli.sim_speed import INSTANT_SIM

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

RIG = """
[rig]
seed = 4
[rig.effects.sensor_scale]
enabled = true
gain_error_ppm = [3000.0, 0.0, 0.0, -2000.0, 0.0, 0.0]
[rig.effects.leg_compliance]
enabled = true
c_mm_per_kn = 0.006
"""


def _run(tmp: Path, name: str, plan: Path, *args: str, answers: str | None = None) -> tuple[int, str, Path]:
    """The run in this process (tests/cli/in_process.py): its exit code, what it printed and its folder."""
    done = hilcal_in_process("run", "--sim", "--operator", "T", "--sim-config", str(tmp / "sim.toml"), "--plan",
                             str(plan), "--out", str(tmp / name), *args, input=answers,
                             env={"HILCAL_RECORDS": str(tmp / f"{name}.sqlite"), "COLUMNS": "200"})
    return done.returncode, done.stdout + done.stderr, tmp / name


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory, instant_plan: Path, small_plan: Path
         ) -> dict[str, tuple[int, str, Path]]:
    """The same rig seed twice: physics on (answered at the terminal) and physics off (unattended; the small plan: its
    claim is the refusal, which the first poses already show)."""
    tmp = tmp_path_factory.mktemp("physics")
    (tmp / "sim.toml").write_text(INSTANT_SIM + RIG)
    return {"on": _run(tmp, "on", instant_plan, answers="y\ny\ny\n"),
            "off": _run(tmp, "off", small_plan, "--yes", "--physics", "off")}


def test_the_run_corrects_the_faults_it_finds_and_proves_it_at_the_machine(runs) -> None:
    code, stdout, run = runs["on"]
    assert code == 0, stdout
    report = json.loads((run / "report.json").read_text())
    physics = report["physics"]
    assert physics["problems"] == [] and physics["explained"], "the geometric fit's 30 mm were explained"
    assert physics["geometry_source"] == "fitted together with the effects"
    block = report["compensation"]["compensation_block"]
    # the true reading errors: a gain g reads (1 + g) times the travel, so the correction is -g / (1 + g) of it
    assert block["scale_ppm"][0] == pytest.approx(-3000 / 1.003, abs=10)
    assert block["scale_ppm"][3] == pytest.approx(2000 / 0.998, abs=10)
    # each leg's sag within 3 of its stated standard errors of the rig's 6 µm/kN, and those errors small; the block
    # holds the estimates
    (sag,) = [c for c in physics["corrected"] if c["effect"] == "leg_compliance"]
    values = {v["leg"]: v for v in sag["values"]}
    assert sorted(values) == [1, 2, 3, 4, 5, 6]
    for leg, v in values.items():
        assert abs(v["value"] - 6.0) <= 3 * v["std_error"] and v["std_error"] < 0.9, (leg, v)
        assert block["compliance_mm_per_kn"][leg - 1] == pytest.approx(v["value"] / 1000, rel=1e-6)
    measured = report["verification"]["after"]["rms_position_mm"]
    predicted = physics["predicted_with_physics"]["rms_position_mm"]
    assert predicted / 1.5 <= measured <= 1.5 * predicted
    assert measured <= physics["predicted_geometry_only"]["rms_position_mm"] / 5
    state = json.loads((run / "sim_state.json").read_text())["banks"]
    words = np.frombuffer(bytes.fromhex(state["comp_live"]), dtype=">u2").tolist()
    held = block_from_words(words)
    assert held["scale_ppm"][0] == pytest.approx(block["scale_ppm"][0], abs=1e-3), "the controller holds the block"
    assert report["upload"]["record"]["compensation_readback_match"] is True
    with Records(run.parent / "on.sqlite") as db:  # the records keep each transducer's reading error, for drift
        kept = db.run_parameters(report["run_id"])
    stroke_range_mm = 4800.0 - 3800.0  # the robot file's leg limits
    assert kept["leg1_reads_long_at_full_stroke_mm"][0] == pytest.approx(3000 / 1.003 * 1e-6 * stroke_range_mm,
                                                                         abs=0.02)


def test_the_approval_screen_opens_with_the_findings(runs) -> None:
    _, stdout, _ = runs["on"]
    approval = stdout[stdout.index("What this run's recording shows beyond the geometry"):]
    approval = approval[:approval.index("Upload the full")]
    assert approval.index("Leg 1 reads 0.30% long") < approval.index("sag under the platform's weight")
    assert "the upload corrects the reading scale of each leg; check its transducer" in approval
    assert "predicted after the upload: max" in approval and "predicted with the geometry alone" in approval
    assert "compensation block: scale -2.99e+03" in approval


def test_without_physics_the_same_rig_is_refused(runs) -> None:
    code, stdout, run = runs["off"]
    assert code == 3, stdout
    assert "exceeds the plausible" in stdout and "nothing uploaded" in stdout
    report = json.loads((run / "report.json").read_text())
    assert report["uploaded"] is False and report["physics"]["enabled"] is False
