"""`hilcal upload` and `hilcal rollback` on CANopen controllers, by station file alone.

The ACME LX-200 (tests/drivers/controller/acme_lx200.eds, a plain ``canopen.LocalNode``:
``tests/drivers/controller/canopen_peer.py``) on python-can's virtual bus, so the commands run in this process: its
leg offsets round-trip exactly (µm integers).
The simulated HX-6 (``hilcal sim --controller canopen --state-file``, a subprocess on its SLCAN pty) killed with
SIGKILL in the middle of an upload: after its restart, ``hilcal upload`` or ``hilcal rollback`` again leave it
holding the new set or the old one, never a mix, every value read back by ``canopen``'s own ``SdoClient``.
"""

from __future__ import annotations

import itertools
import json
import os
import signal
import struct
import time
from pathlib import Path

import canopen
import numpy as np
import pytest
from typer.testing import CliRunner

from drivers.controller.parameter_sets import ParameterSet, ParamsError
from hilcal.protocols.canopen import HEXAPOD_CONTROLLER_EDS
from hilcal.robot import default_robot
from procedures.cli.app import app
from procedures.cli.sim_station import sim_controller_section
from procedures.records import Records, upload_parameter_file
from procedures.sections.controller import open_parameters
from procedures.station import load_station, save_station, station_from_channels
from sim_devices.launcher import spawn_sim_subprocess, stop_sim_subprocess
from tests.drivers.controller.canopen_peer import ACME_EDS, AcmePeer

pytestmark = [pytest.mark.timeout(120),
              # a killed simulator's pty ends python-can's notifier thread of the link that was talking to it
              pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")]
runner = CliRunner()
STATION = Path(__file__).parents[1] / "drivers" / "controller" / "acme_lx200_station.toml"
_n = itertools.count()


def _params_file(path: Path, l0_mm: list[float]) -> Path:
    nominal = ParameterSet.from_robot(default_robot())
    path.write_text(json.dumps({"a_mm": nominal.a_mm, "b_mm": nominal.b_mm, "l0_mm": l0_mm}))
    return path


def test_acme_upload_and_rollback_round_trip_exactly(tmp_path: Path) -> None:
    channel = f"acme-cli-{next(_n)}-{time.monotonic_ns()}"
    (tmp_path / "acme_lx200.eds").write_text(ACME_EDS.read_text())
    (tmp_path / "station.toml").write_text(STATION.read_text().replace('channel = "acme-lx200"',
                                                                        f'channel = "{channel}"'))
    peer = AcmePeer(channel)
    try:
        db = str(tmp_path / "records.sqlite")
        new = [3800.123, 3799.877, 3800.5, 3801.25, 3799.001, 3800.0]
        result = runner.invoke(app, ["upload", str(_params_file(tmp_path / "p.json", new)), "--station",
                                     str(tmp_path / "station.toml"), "--yes", "--save", "--records", db])
        assert result.exit_code == 0, result.output
        assert peer.zero_um == [round(v * 1000) for v in new] and peer.kept_um == peer.zero_um
        result = runner.invoke(app, ["rollback", "--station", str(tmp_path / "station.toml"), "--records", db])
        assert result.exit_code == 0, result.output
        assert "rolled_back" in result.output and peer.zero_um == [3800000] * 6
        with Records(db) as records:
            rows = [e for e in records.history(10) if e.get("kind") == "upload"]
        assert [r["record"]["operation"] for r in rows] == ["rollback", "upload"]
        assert [w["object"].split()[0] for w in rows[0]["record"]["writes"][:6]] == [
            f"0x4100:{k}@5" for k in range(1, 7)]
    finally:
        peer.close()



def test_acme_is_checked_by_its_station_file_alone(tmp_path: Path) -> None:
    """`hilcal check` on the device it was not written for: identity from 1018h, state, the leg offsets it holds and
    its checksum object beside the one the offsets read should give; nothing written."""
    channel = f"acme-check-{next(_n)}-{time.monotonic_ns()}"
    (tmp_path / "acme_lx200.eds").write_text(ACME_EDS.read_text())
    text = STATION.read_text().replace('channel = "acme-lx200"', f'channel = "{channel}"')
    (tmp_path / "station.toml").write_text(text[:text.index("[cmm]")])  # the controller alone is checked
    peer = AcmePeer(channel)
    try:
        result = runner.invoke(app, ["check", "--station", str(tmp_path / "station.toml"), "--json"])
        assert result.exit_code == 0, result.output
        (controller,) = json.loads(result.stdout)["devices"]
        assert controller["identity"]["vendor_id"] == 0xAC and controller["identity"]["node_id"] == 5
        parameters = controller["parameters"]
        assert parameters["geometry"]["l0_mm"] == [v / 1000 for v in peer.zero_um]
        assert parameters["checksum"] is not None and parameters["checksum"] == parameters["checksum_expected"]
        assert peer.kept_um == peer.zero_um and controller["problems"] == []
        text = runner.invoke(app, ["check", "--station", str(tmp_path / "station.toml")])
        assert text.exit_code == 0, text.output
        assert "stop: halt, controlword bit 8; e-stop: quick stop, controlword 0002h" in text.output
    finally:
        peer.close()

def _sdo_geometry(channel: str) -> np.ndarray:
    """The HX-6's 42 geometry values read by canopen's own SdoClient (REAL32 little-endian, as its EDS says)."""
    network = canopen.Network()
    network.connect(interface="slcan", channel=channel, sleep_after_open=0)
    try:
        node = network.add_node(1, str(HEXAPOD_CONTROLLER_EDS))
        values = [struct.unpack("<f", node.sdo.upload(0x2100 + 0x10 * part + leg, axis))[0]
                  for part in (0, 1) for leg in range(6) for axis in (1, 2, 3)]
        values += [struct.unpack("<f", node.sdo.upload(0x2120, leg))[0] for leg in range(1, 7)]
        return np.array(values)
    finally:
        network.disconnect()


def _start(tmp: Path) -> tuple[object, Path, str]:
    proc, channels = spawn_sim_subprocess(None, ["--controller", "canopen", "--state-file", str(tmp / "sim.json")],
                                          log_path=tmp / "sim.log")
    station = station_from_channels(channels, None, sim_controller_section(channels))
    station = station.model_copy(update={"records": tmp / "records.sqlite"})
    save_station(station, tmp / "station.toml")
    return proc, tmp / "station.toml", channels["can"]["channel"]


@pytest.mark.parametrize("again", ["upload", "rollback"])
def test_a_controller_killed_mid_upload_holds_the_old_set_or_the_new_one(tmp_path: Path, again: str) -> None:
    proc, station_file, channel = _start(tmp_path)
    try:
        old = _sdo_geometry(channel)
        new = old.copy()
        new[:36] += np.linspace(0.1, 3.6, 36)
        new[36:] += np.array([0.5, -0.25, 0.125, 1.0, -1.0, 0.75])
        params_file = tmp_path / "new.json"
        params_file.write_text(json.dumps(ParameterSet.from_vector(new).model_dump()))
        client = open_parameters(load_station(station_file))
        write, count = client.link.write, itertools.count()

        def kill_midway(slot, raw):
            if next(count) == 20:  # a1..b1: twenty of the 42 written, then the controller dies
                os.kill(proc.pid, signal.SIGKILL)
            write(slot, raw)

        client.link.write = kill_midway
        with Records(tmp_path / "records.sqlite") as db, pytest.raises(ParamsError) as err:
            upload_parameter_file(client, params_file, db, "T", True, True, lambda _: True)
        client.close()
        record = err.value.record
        assert record.outcome == "failed" and sum(w.ok for w in record.writes) == 20
        proc.wait(5)
        proc, station_file, channel = _start(tmp_path)  # the same state file: what it stored
        assert np.array_equal(_sdo_geometry(channel), old.astype(np.float32)), "restarted with the stored set"
        args = (["upload", str(params_file), "--yes", "--save"] if again == "upload" else ["rollback"])
        result = runner.invoke(app, [*args, "--station", str(station_file)])
        assert result.exit_code == 0, result.output
        held = _sdo_geometry(channel)
        expected = new if again == "upload" else old
        assert np.array_equal(held, expected.astype(np.float32)), f"after hilcal {again}: {held - expected}"
    finally:
        stop_sim_subprocess(proc)
