"""``hilcal sim --controller canopen`` as a separate process with a state file: the channels it prints, and a
simulator killed (SIGKILL) in the middle of writing a parameter set restarts holding the last stored set, its stored
communication parameters included, as a device's non-volatile memory does. canopen's ``RemoteNode`` is the host."""

from __future__ import annotations

import os
import signal
import subprocess
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import canopen
import numpy as np
import pytest

from hilcal.protocols.canopen import HEXAPOD_CONTROLLER_EDS
from hilcal.robot import default_robot
from sim_devices.launcher import spawn_sim_subprocess, stop_sim_subprocess

pytestmark = pytest.mark.timeout(90)

SDO_TIMEOUT_S = 2.0
"""canopen's SdoClient waits 0.3 s for an answer by default; a busy 2-core CI machine can take longer."""

ROBOT = default_robot()


class Host:
    """A canopen network on the simulator's SLCAN channel with the HX-6 as a RemoteNode."""

    def __init__(self, channels: dict[str, Any]) -> None:
        self.net = canopen.Network()
        self.net.connect(interface="slcan", channel=channels["can"]["channel"], sleep_after_open=0)
        self.node = canopen.RemoteNode(channels["canopen"]["node_ids"][0], channels["canopen"]["eds"])
        self.node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
        self.net.add_node(self.node)

    def close(self) -> None:
        self.net.disconnect()


@pytest.fixture
def spawn(tmp_path: Path) -> Iterator[Any]:
    procs: list[subprocess.Popen[bytes]] = []

    def start(*args: str) -> tuple[subprocess.Popen[bytes], dict[str, Any]]:
        proc, channels = spawn_sim_subprocess(None, args, log_path=tmp_path / f"sim{len(procs)}.log")
        procs.append(proc)
        return proc, channels

    yield start
    for proc in procs:
        stop_sim_subprocess(proc)


def test_killed_mid_upload_restarts_with_the_stored_set(tmp_path: Path, spawn) -> None:
    state = tmp_path / "state.json"
    proc, channels = spawn("--controller", "canopen", "--state-file", str(state))
    assert channels["controller"] == {"protocol": "canopen"}
    assert channels["canopen"]["eds"] == str(HEXAPOD_CONTROLLER_EDS) and channels["canopen"]["node_ids"] == [1]
    assert "modbus" not in channels
    host = Host(channels)
    node = host.node
    try:
        stored = ROBOT.l0 + np.array([0.5, -0.25, 0.125, 1.0, -1.0, 0.75])
        for leg in range(6):
            node.sdo[0x2120][leg + 1].raw = float(stored[leg])
        node.sdo[0x1017].raw = 333
        node.sdo.download(0x1010, 1, b"save")  # everything: the set and the communication parameters
        for leg in range(3):  # an upload in the middle: half the new set written, nothing stored
            node.sdo[0x2120][leg + 1].raw = float(stored[leg] + 2.0)
        assert node.sdo[0x2120][1].raw == np.float32(stored[0] + 2.0)
    finally:
        host.close()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(10)
    _, channels = spawn("--controller", "canopen", "--state-file", str(state))
    host = Host(channels)
    try:
        live = np.array([host.node.sdo[0x2120][leg].raw for leg in range(1, 7)])
        assert np.array_equal(live, stored.astype(np.float32))
        assert host.node.sdo[0x1017].raw == 333
        assert host.node.nmt.wait_for_heartbeat(1.0) == "PRE-OPERATIONAL"
    finally:
        host.close()
