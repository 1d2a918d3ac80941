"""A whole `hilcal run --station FILE` with a CANopen controller the driver was not written for.

The ACME LX-200 (tests/drivers/controller/canopen_peer.py, a plain ``canopen.LocalNode`` with vendor objects at
4000h-4101h, INTEGER32 µm, only the leg offsets held) drives the simulated rig here: its axis lengths are the rig's
readings plus whatever its zero lengths (4100h) moved since the rig was set up, as on a real axis whose leg offset
changes. The simulated CMM measures the rig over TCP. The station file is the one docs/controllers.md writes for the
device, with the CMM's URL and alignment; the run goes through python-can's virtual bus, so it runs in this
process. The run must move, measure, identify, upload the leg offsets through the mapping (read back), verify and
complete, and the verification after the upload must be what the uploaded offsets predict.
"""

from __future__ import annotations

import itertools
import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from hilcal.robot import default_robot
from procedures.cli.app import app
from sim_devices.cmm.server import start_cmm_server
from sim_devices.rig.rig import SimulatedRig
from sim_devices.sim_config import SimConfig
from sim_devices.simulator import published_alignment
from tests.cli.others.rig_support import RigView
from tests.drivers.controller.canopen_peer import ACME_EDS, UM, AcmePeer

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]
STATION = Path(__file__).parents[2] / "drivers" / "controller" / "acme_lx200_station.toml"
_n = itertools.count()


class AcmeOnRig(AcmePeer):
    """The LX-200 moving the rig: once its axes reach their target, the rig's legs read the axis lengths less what
    the zero lengths moved since start (a larger zero length reports the same leg longer)."""

    def __init__(self, channel: str, rig: SimulatedRig, lock: threading.Lock) -> None:
        self.rig, self.rig_lock = rig, lock
        super().__init__(channel)
        self.start_zero_um = list(self.zero_um)
        with self._lock:
            self.position_um = [float(v) for v in np.round(rig.reported_lengths() * UM)]
            self.target_um = list(self.position_um)

    def arrived(self) -> None:
        moved = np.subtract(self.zero_um, self.start_zero_um)
        with self.rig_lock:
            self.rig.move_to_lengths((np.array(self.position_um) - moved) / UM)


@pytest.fixture(scope="module")
def acme_run(tmp_path_factory: pytest.TempPathFactory, small_plan: Path) -> dict:
    tmp = tmp_path_factory.mktemp("acme_run")
    robot = default_robot()
    config = SimConfig.model_validate({"cmm": {"time_scale": 0.0},
                                       "rig": {"seed": 3, "temperature": {"drift_k_per_h": 0.0, "amplitude_k": 0.0}}})
    rig = SimulatedRig(robot, config.rig.rig_config(robot))
    lock = threading.Lock()
    rig.move_to_lengths(rig.controller_ik(robot.home))
    cmm = start_cmm_server(robot, RigView(rig, lock), config.cmm.server_config(config.rig.seed))  # type: ignore[arg-type]
    channel = f"acme-run-{next(_n)}-{time.monotonic_ns()}"
    peer = AcmeOnRig(channel, rig, lock)
    try:
        alignment = published_alignment(rig, config.cmm.alignment_error_mm, config.cmm.alignment_error_deg,
                                        config.rig.seed)
        text = STATION.read_text().replace('channel = "acme-lx200"', f'channel = "{channel}"')
        text = text[:text.index("[cmm]")] + (f'[cmm]\nurl = "{cmm.socket_url}"\nalignment = '
                                             f"{json.dumps(alignment.tolist())}\n")
        (tmp / "acme_lx200.eds").write_text(ACME_EDS.read_text())
        (tmp / "station.toml").write_text(text)
        start_zero = list(peer.zero_um)
        result = CliRunner().invoke(app, ["run", "--station", str(tmp / "station.toml"), "--plan", str(small_plan),
                                          "--operator", "T", "--out", str(tmp / "run")],
                                    input="y\ny\ny\n",  # answered at the terminal: the approval is printed
                                    env={"HILCAL_RECORDS": str(tmp / "records.sqlite"), "COLUMNS": "200"})
        return {"result": result, "run": tmp / "run", "peer_zero_um": list(peer.zero_um),
                "peer_kept_um": list(peer.kept_um), "start_zero_um": start_zero, "executes": peer.executes,
                "rig": rig}
    finally:
        peer.close()
        cmm.close()


def test_the_run_completes_on_a_device_it_was_not_written_for(acme_run) -> None:
    result = acme_run["result"]
    assert result.exit_code == 0, result.output
    report = json.loads((acme_run["run"] / "report.json").read_text())
    assert report["status"] == "complete" and report["uploaded"]
    assert acme_run["executes"] > 0, "the device executed setpoints through its apply object (4001h)"
    assert "leg offsets l0 only" in result.output and "read back: matches" in result.output
    # the approval says what the full geometry would give only as what this controller cannot take, and what stays
    assert "with the joint positions too (this controller holds the leg offsets only)" in result.output
    assert "predicted with the geometry alone" not in result.output
    assert "left uncompensated by the offsets over 64 workspace poses" in result.output


def test_the_leg_offsets_are_uploaded_through_the_mapping_and_saved(acme_run) -> None:
    report = json.loads((acme_run["run"] / "report.json").read_text())
    assert report["compensation"]["mode"] == "offsets_only"
    uploaded = report["compensation"]["uploaded_parameters"]["l0_mm"]
    assert acme_run["peer_zero_um"] == [round(v * 1000) for v in uploaded] != acme_run["start_zero_um"]
    assert acme_run["peer_kept_um"] == acme_run["peer_zero_um"], "stored with 1010h"
    writes = [w["object"].split()[0] for w in report["upload"]["record"]["writes"] if w["ok"]]
    assert [w for w in writes if w.startswith("0x4100")] == [f"0x4100:{k}@5" for k in range(1, 7)]


def test_the_verification_after_measures_what_the_offsets_alone_predict(acme_run) -> None:
    """The device keeps its joint positions, so the rig's joint errors stay: the prediction must be the offsets'
    (not the full geometry's few µm), and the verification after the upload must measure it."""
    report = json.loads((acme_run["run"] / "report.json").read_text())
    before, after = report["verification"]["before"], report["verification"]["after"]
    predicted = report["compensation"]["predicted_held_out"]
    full = report["table7"]["predicted_after"]["ls"]["position_mm"]
    assert after["rms_position_mm"] < before["rms_position_mm"] / 5
    assert predicted["max_position_mm"] > 10 * full["max"], "the prediction is the offsets', not the full geometry's"
    for key in ("max_position_mm", "rms_position_mm"):
        assert predicted[key] / 1.5 <= after[key] <= 1.5 * predicted[key], (key, after[key], predicted[key])
    page = (acme_run["run"] / "report.html").read_text()
    assert "predicted for the leg offsets uploaded" in page and "predicted with the geometry alone" not in page
