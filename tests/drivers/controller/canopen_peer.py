"""A CANopen controller the driver was not written for: the ACME LX-200 of ``acme_lx200.eds`` (vendor objects at
4000h-4101h, INTEGER32 µm, only the leg offsets held, a checksum object), served by a plain ``canopen.LocalNode`` on
python-can's virtual bus, as its EDS [Comments] describe it.

Device control after CiA 402-2 (the states coded in 6041h bits 0-6, bit 10 target reached); axis positions move
towards the executed setpoints at ``speed_mm_s``; zero lengths writable only when not in operation enabled (abort
08000022h); 1010h "save" keeps them and ``power_cycle`` loads the kept ones. ``fail_write`` makes one object's next
write abort (06090030h), ``silence`` stops the heartbeat and every SDO answer.
"""

from __future__ import annotations

import struct
import threading
import zlib
from pathlib import Path

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError

ACME_EDS = Path(__file__).with_name("acme_lx200.eds")
NODE_ID = 5
STATUS = {"switch_on_disabled": 0x0040, "ready": 0x0021, "switched_on": 0x0023, "enabled": 0x0027, "fault": 0x0008}
UM = 1000.0


class AcmePeer:
    """The LX-200 on ``can.Bus(interface="virtual", channel=channel)``; ``close()`` stops it."""

    def __init__(self, channel: str, *, node_id: int = NODE_ID, speed_mm_s: float = 5000.0,
                 start_mm: float = 4200.0) -> None:
        self.node_id = node_id
        self.speed_mm_s = speed_mm_s
        self.state = "switch_on_disabled"
        od = canopen.import_od(str(ACME_EDS), node_id)
        self.zero_um = [int(od[0x4100][k].default) for k in range(1, 7)]
        self.kept_um = list(self.zero_um)
        self.setpoint_um = [0] * 6
        self.position_um = [start_mm * UM] * 6
        self.target_um = list(self.position_um)
        self.executes = 0
        self.fail_next: dict[tuple[int, int], int] = {}
        self.silent = False
        self._lock = threading.Lock()
        self.network = canopen.Network(can.Bus(interface="virtual", channel=channel, receive_own_messages=False))
        self.network.NOTIFIER_CYCLE = 0.05
        self.network.connect()
        self.node = canopen.LocalNode(node_id, od)
        self.network.add_node(self.node)
        self.node.add_write_callback(self._on_write)
        self.node.add_read_callback(self._on_read)
        self._on_request = self.node.sdo.on_request
        self.network.subscribe(0x600 + node_id, self._request)
        self.network.unsubscribe(0x600 + node_id, self._on_request)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._servo, daemon=True)
        self._thread.start()
        self.node.nmt.state = "PRE-OPERATIONAL"
        self.node.nmt.start_heartbeat(50)

    # ------------------------------------------------------------------ the device

    def _request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not self.silent:
            self._on_request(can_id, data, timestamp)

    def _on_read(self, index: int, subindex: int, od: object) -> int | None:
        with self._lock:
            if index == 0x6041:
                word = STATUS[self.state]
                if self.state == "enabled" and self.position_um == self.target_um:
                    word |= 1 << 10
                return word
            if index == 0x4010:
                return round(self.position_um[subindex - 1])
            if index == 0x4100:
                return self.zero_um[subindex - 1]
            if index == 0x4101:
                return zlib.crc32(struct.pack("<6l", *self.zero_um))
        return None

    def _on_write(self, index: int, subindex: int, od: object, data: bytes) -> None:
        code = self.fail_next.pop((index, subindex), None)
        if code is not None:
            raise SdoAbortedError(code)
        with self._lock:
            if index == 0x6040:
                self._control(struct.unpack("<H", data)[0])
            elif index == 0x4000:
                self.setpoint_um[subindex - 1] = struct.unpack("<l", data)[0]
            elif index == 0x4001:
                if self.state != "enabled":
                    raise SdoAbortedError(0x08000022)
                self.target_um = [float(v) for v in self.setpoint_um]
                self.executes += 1
            elif index == 0x4100:
                if self.state == "enabled":
                    raise SdoAbortedError(0x08000022)
                value = struct.unpack("<l", data)[0]
                if not 100_000 <= value <= 20_000_000:
                    raise SdoAbortedError(0x06090030)
                self.zero_um[subindex - 1] = value
            elif index == 0x1010 and data == b"save":
                self.kept_um = list(self.zero_um)
            elif index == 0x1010:
                raise SdoAbortedError(0x08000020)

    def _control(self, word: int) -> None:
        command = word & 0x8F
        if self.state == "fault":
            if word & 0x80:
                self.state = "switch_on_disabled"
            return
        if command & 0x02 == 0 or command & 0x06 == 0x02:  # disable voltage, quick stop
            self.state = "switch_on_disabled"
        elif command & 0x07 == 0x06:
            self.state = "ready"
        elif command & 0x0F == 0x07 and self.state in ("ready", "enabled"):
            self.state = "switched_on"
        elif command & 0x0F == 0x0F and self.state in ("switched_on", "enabled"):
            if self.state != "enabled":
                self.target_um = list(self.position_um)
            self.state = "enabled"
            if word & 0x100:  # halt
                self.target_um = list(self.position_um)

    def _servo(self) -> None:
        step = self.speed_mm_s * UM * 0.002
        while not self._stop.wait(0.002):
            with self._lock:
                if self.state != "enabled" or self.position_um == self.target_um:
                    continue
                self.position_um = [t if abs(t - p) <= step else p + step * (1 if t > p else -1)
                                    for p, t in zip(self.position_um, self.target_um, strict=True)]
                if self.position_um == self.target_um:
                    self.arrived()

    def arrived(self) -> None:
        """The axes have just reached their target (called under the device's lock); nothing here."""

    # ------------------------------------------------------------------ for the tests

    def fault(self, code: int = 0xFF10) -> None:
        """A fault with an emergency message (code, error register generic + manufacturer)."""
        with self._lock:
            self.state = "fault"
        self.node.emcy.send(code, 0x81)

    def power_cycle(self) -> None:
        """Lose what was not stored, load what was, boot again (a boot-up message)."""
        with self._lock:
            self.zero_um = list(self.kept_um)
            self.state = "switch_on_disabled"
            self.target_um = list(self.position_um)
        self.network.send_message(0x700 + self.node_id, [0])  # boot-up

    def silence(self, silent: bool = True) -> None:
        """Stop (or resume) the heartbeat and every SDO answer: a node whose cable was pulled."""
        self.silent = silent
        if silent:
            self.node.nmt.stop_heartbeat()
        else:
            self.node.nmt.start_heartbeat(50)

    def close(self) -> None:
        self._stop.set()
        self.node.nmt.stop_heartbeat()
        self.network.disconnect()
