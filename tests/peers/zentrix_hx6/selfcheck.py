"""Self-check of the simulated Zentrix HX-6, driven as a customer would over CANopen.

Run: python selfcheck.py   (exit code 0 on success, a few seconds at most)
"""

from __future__ import annotations

import logging
import os
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import canopen
from canopen.sdo import SdoAbortedError, SdoCommunicationError

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from device import EDS_PATH, PerfectPlant, ZentrixHX6  # type: ignore[no-redef]
else:
    from .device import EDS_PATH, PerfectPlant, ZentrixHX6

NODE_ID = 5
SAVE = 0x65766173
LOAD = 0x64616F6C
IN_MOTION, IN_POSITION, FAULT, GEOMETRY_MODIFIED = 0x0001, 0x0002, 0x0004, 0x0010


def check(condition: bool, what: str) -> None:
    """Print a PASS line or stop the self-check with a failure."""
    if not condition:
        raise SystemExit(f"FAIL: {what}")
    print(f"PASS: {what}")


def expect_abort(code: int, action: Callable[[], object], what: str) -> None:
    """Check that an SDO access is refused with the given abort code."""
    try:
        action()
    except SdoAbortedError as exc:
        check(exc.code == code, f"{what} -> abort 0x{exc.code:08X} (expected 0x{code:08X})")
        return
    check(False, f"{what} -> no abort (expected 0x{code:08X})")


def wait_until(condition: Callable[[], bool], timeout: float = 1.0) -> bool:
    """Poll until condition() is true or the timeout expires."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.005)
    return condition()


class HeartbeatLog:
    """Records the NMT state bytes the node sends on 700h + node-ID."""

    def __init__(self, network: canopen.Network) -> None:
        self.states: list[int] = []
        self._lock = threading.Lock()
        network.subscribe(0x700 + NODE_ID, self._on_message)

    def _on_message(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            self.states.append(data[0])

    def clear(self) -> None:
        with self._lock:
            self.states.clear()

    def seen(self, state: int) -> bool:
        with self._lock:
            return state in self.states


def main() -> None:
    # The STOPPED check provokes an SDO timeout on purpose; keep the client quiet about it.
    logging.getLogger("canopen.sdo.client").setLevel(logging.ERROR)
    channel = f"zentrix-selfcheck-{os.getpid()}"
    storage = Path(tempfile.mkdtemp(prefix="zentrix_hx6_")) / "nvm.json"
    plant = PerfectPlant()

    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.1
    network.connect(interface="virtual", channel=channel)
    heartbeats = HeartbeatLog(network)
    remote = network.add_node(NODE_ID, str(EDS_PATH))
    device = ZentrixHX6(channel, NODE_ID, plant=plant, storage_path=storage)
    try:
        check(wait_until(lambda: heartbeats.seen(0x00)), "boot-up message received")
        identity = [remote.sdo[0x1018][sub].raw for sub in range(1, 5)]
        check(identity == [0x5A454E58, 0x00480006, 0x00010003, 0x0006D3A1],
              f"identity 1018h = {[hex(v) for v in identity]}")
        check(remote.sdo[0x1008].raw == "Zentrix HX-6", "device name 1008h (segmented upload)")

        remote.sdo[0x1017].raw = 100
        heartbeats.clear()
        check(wait_until(lambda: heartbeats.seen(0x7F), 0.5), "heartbeat PRE-OPERATIONAL")
        remote.nmt.state = "OPERATIONAL"
        check(wait_until(lambda: heartbeats.seen(0x05), 0.5), "heartbeat OPERATIONAL")

        actual = [remote.sdo[0x2001][leg].raw for leg in range(1, 7)]
        check(actual == [383_175_995] * 6, f"power-on lengths {actual} nm (mid-stroke)")
        deltas = [1_234_567, -2_000_000, 500, 0, 12_000_000, -24_000_000]
        targets = [length + delta for length, delta in zip(actual, deltas, strict=True)]
        for leg, target in enumerate(targets, start=1):
            remote.sdo[0x2000][leg].raw = target
        remote.sdo[0x2010].raw = 0x0000
        remote.sdo[0x2010].raw = 0x0001
        check(remote.sdo[0x2011].raw & IN_MOTION != 0, "status IN_MOTION after start")
        check(wait_until(lambda: remote.sdo[0x2011].raw & IN_POSITION != 0),
              "status IN_POSITION after the move")
        reached = [remote.sdo[0x2001][leg].raw for leg in range(1, 7)]
        check(reached == targets, "actual lengths equal targets")
        check(device.moves == 1 and remote.sdo[0x2012].raw == 1, "one move executed")

        remote.sdo[0x2010].raw = 0x0001
        check(device.moves == 1, "start bit held high does not start another move")
        remote.sdo[0x2010].raw = 0x0000

        expect_abort(0x06090031, lambda: remote.sdo[0x2000][1].__setattr__(
            "raw", actual[0] + 25_000_001), "target above stroke")
        expect_abort(0x06090032, lambda: remote.sdo[0x2000][1].__setattr__(
            "raw", actual[0] - 25_000_001), "target below stroke")
        expect_abort(0x06010002, lambda: remote.sdo[0x2001][1].__setattr__("raw", 0),
                     "write to read-only 2001h")
        expect_abort(0x06020000, lambda: remote.sdo.upload(0x2500, 0), "unknown object 2500h")
        expect_abort(0x06090011, lambda: remote.sdo.upload(0x2000, 7), "2000h sub-index 7")
        expect_abort(0x06090030, lambda: remote.sdo[0x2103][7].__setattr__("raw", float("nan")),
                     "NaN geometry value")
        expect_abort(0x08000020, lambda: remote.sdo[0x1010][1].__setattr__("raw", 0x12345678),
                     "store with a wrong signature")

        unmoved = remote.sdo[0x2001][3].raw
        remote.sdo[0x2103][7].raw = 360.5
        check(remote.sdo[0x2103][7].raw == 360.5, "leg 3 zero length written")
        check(remote.sdo[0x2001][3].raw - unmoved == 360_500_000 - 358_175_995,
              "zero length shifts the reported length of an unmoved leg")
        check(remote.sdo[0x2011].raw & GEOMETRY_MODIFIED != 0, "status GEOMETRY_MODIFIED")
        remote.sdo[0x1010][1].raw = SAVE
        check(remote.sdo[0x2011].raw & GEOMETRY_MODIFIED == 0, "stored with 1010h sub 1")
        check(remote.sdo[0x1010][1].raw == 1, "1010h sub 1 reads 'saves on command'")

        remote.sdo.RESPONSE_TIMEOUT = 0.15
        remote.nmt.state = "STOPPED"
        time.sleep(0.02)
        try:
            remote.sdo.upload(0x1000, 0)
            check(False, "no SDO answer in STOPPED")
        except SdoCommunicationError:
            check(True, "no SDO answer in STOPPED")
        remote.nmt.state = "PRE-OPERATIONAL"
        time.sleep(0.02)
        remote.sdo.RESPONSE_TIMEOUT = 0.3
        check(remote.sdo[0x1000].raw == 0, "SDO answered again in PRE-OPERATIONAL")
    finally:
        device.close()

    heartbeats.clear()
    device = ZentrixHX6(channel, NODE_ID, plant=plant, storage_path=storage)
    try:
        check(wait_until(lambda: heartbeats.seen(0x00)), "boot-up after power cycle")
        check(remote.sdo[0x2103][7].raw == 360.5, "stored zero length survives power cycle")
        check(remote.sdo[0x1017].raw == 100, "stored heartbeat time survives power cycle")
        check(remote.sdo[0x2001][1].raw == targets[0], "platform did not move on power cycle")

        remote.sdo[0x1011][1].raw = LOAD
        check(remote.sdo[0x2103][7].raw == 360.5, "restore takes effect only after reset")
        heartbeats.clear()
        remote.nmt.send_command(0x81)
        check(wait_until(lambda: heartbeats.seen(0x00)), "boot-up after NMT reset node")
        zero = remote.sdo[0x2103][7].raw
        check(abs(zero - 358.176) < 1e-4, f"factory zero length {zero} after reset")
        check(remote.sdo[0x1017].raw == 500, "factory heartbeat time after reset")
    finally:
        device.close()
        network.disconnect()
    print("Zentrix HX-6 self-check passed")


if __name__ == "__main__":
    main()
