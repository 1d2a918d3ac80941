"""`hilcal run --sim --yes --controller canopen` on a rig with concealed physics: the whole run through the simulated
HX-6 CANopen controller (its EDS and the station mapping of ``procedures.cli.sim_station.HX6_MAPPING``).

The rig's transducers of legs 1 and 4 read 0.30 % long and 0.20 % short and its legs sag 6 µm/kN (the physics test's
rig). The run must diagnose them, upload the geometry and the compensation terms through the mapping (every SDO write
recorded, read back, the checksum object compared, stored with 1010h), and verify after the upload what its
diagnosis predicted (within 1.5 times). One run, shared by the module.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import pytest

from procedures.cli.sim_station import HX6_MAPPING
from procedures.sections.controller import CanopenControllerSection
from tests.cli.in_process import hilcal_in_process
from tests.cli.sim_speed import INSTANT_SIM

pytestmark = pytest.mark.timeout(300)
ROOT = Path(__file__).resolve().parents[2]
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


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory, instant_plan: Path) -> tuple[int, str, Path]:
    tmp = tmp_path_factory.mktemp("canopen_run")
    (tmp / "sim.toml").write_text(INSTANT_SIM + RIG)
    env = {"HILCAL_RECORDS": str(tmp / "records.sqlite"), "COLUMNS": "200"}
    proc = hilcal_in_process("run", "--sim", "--yes", "--operator", "T", "--controller", "canopen", "--sim-config",
                             str(tmp / "sim.toml"), "--plan", str(instant_plan), "--out", str(tmp / "run"), env=env)
    return proc.returncode, proc.stdout + proc.stderr, tmp / "run"


@pytest.mark.slow
def test_the_canopen_run_completes_and_verifies_what_it_predicted(run) -> None:
    code, output, out = run
    assert code == 0, output
    report = json.loads((out / "report.json").read_text())
    predicted = report["physics"]["predicted_with_physics"]
    after = report["verification"]["after"]
    assert after["rms_position_mm"] <= 1.5 * predicted["rms_position_mm"]
    assert after["max_position_mm"] <= 1.5 * predicted["max_position_mm"]
    assert (out / "sim_controller.txt").read_text() == "canopen"


@pytest.mark.slow
def test_the_compensation_terms_went_through_the_mapping(run) -> None:
    code, output, out = run
    assert code == 0, output
    report = json.loads((out / "report.json").read_text())
    block = report["compensation"]["compensation_block"]
    assert block["scale_ppm"][0] == pytest.approx(-3000 / 1.003, abs=30)
    upload = report["upload"]
    record = upload["record"]
    assert record["endpoint"].startswith("canopen://slcan/") and record["outcome"] == "committed"
    written = {w["object"].split()[0]: w["ok"] for w in record["writes"]}
    for leg in range(1, 7):  # the EDS's 2201h reading scale and 2203h compliance, sub-index = leg
        assert written[f"0x2201:{leg}@1"] and written[f"0x2203:{leg}@1"]
    assert record["live_readback_match"] and record["compensation_readback_match"] and record["checksum_match"]
    assert upload["outcome"] == "saved" and upload["save_record"]["writes"][-1]["object"].startswith("0x1010:1@1")


def test_the_example_station_file_holds_the_simulated_mapping() -> None:
    data = tomllib.loads((ROOT / "examples" / "stations" / "hx6_sim.toml").read_text())["controller"]
    example = CanopenControllerSection.model_validate(data).mapping()
    ours = CanopenControllerSection.model_validate({"kind": "canopen", "eds": "builtin:hexapod_controller",
                                                    "node_id": 1, **HX6_MAPPING}).mapping()
    assert example == ours
