"""The controller's CAN frames: encode and decode through ``hilcal/protocols/controller.dbc`` with the rolling
counter and checksum of every frame, and the receive-side counts of the CAN driver.
"""

from __future__ import annotations

from dataclasses import dataclass

import can
import cantools

from drivers.controller.base import FrameError
from hilcal.protocols import controller_dbc_text
from hilcal.protocols.checksums import (
    CAN_CHECKSUM_BYTE,
    CAN_COUNTER_BYTE,
    CAN_COUNTER_MODULO,
    CAN_PAYLOAD_BYTES,
    can_frame_checksum,
)


class UnknownFrame(FrameError):
    """A frame ID that is not in the controller database (other traffic on the bus)."""


class FrameLengthError(FrameError):
    pass


class ChecksumError(FrameError):
    pass


@dataclass(frozen=True)
class DecodedFrame:
    name: str
    signals: dict[str, int]

    @property
    def counter(self) -> int:
        return self.signals["Counter"]


class FrameCodec:
    """Controller frames <-> raw signal values via the DBC; sets and verifies counter and checksum."""

    def __init__(self) -> None:
        self.db = cantools.database.load_string(controller_dbc_text(), "dbc")
        self._by_id = {m.frame_id: m for m in self.db.messages}
        self._by_name = {m.name: m for m in self.db.messages}
        for m in self.db.messages:
            layout = {s.name: (s.start, s.length) for s in m.signals}
            if (
                m.length != CAN_PAYLOAD_BYTES
                or layout.get("Counter") != (8 * CAN_COUNTER_BYTE, 4)
                or layout.get("Checksum") != (8 * CAN_CHECKSUM_BYTE, 8)
            ):
                raise FrameError(f"DBC message {m.name}: counter/checksum not at bytes {CAN_COUNTER_BYTE}/"
                                 f"{CAN_CHECKSUM_BYTE}")

    def frame_id(self, name: str) -> int:
        return self._by_name[name].frame_id

    def sent_by_controller(self, frame_id: int) -> bool:
        return "CONTROLLER" in self._by_id[frame_id].senders

    def encode(self, name: str, signals: dict[str, int], counter: int) -> can.Message:
        message = self._by_name[name]
        try:
            payload = message.encode({**signals, "Counter": counter % CAN_COUNTER_MODULO, "Checksum": 0},
                                     scaling=False, strict=True)
        except (cantools.database.EncodeError, KeyError) as err:
            raise FrameError(f"cannot encode {name} {signals}: {err}") from err
        data = bytearray(payload)
        data[CAN_CHECKSUM_BYTE] = can_frame_checksum(message.frame_id, data)
        return can.Message(arbitration_id=message.frame_id, data=data, is_extended_id=False)

    def decode(self, frame_id: int, data: bytes) -> DecodedFrame:
        """Check length and checksum, then decode raw signal values; a FrameError subclass otherwise."""
        message = self._by_id.get(frame_id)
        if message is None:
            raise UnknownFrame(f"frame ID 0x{frame_id:03X} is not a controller frame")
        if len(data) != message.length:
            raise FrameLengthError(f"{message.name}: {len(data)} bytes instead of {message.length}")
        expected = can_frame_checksum(frame_id, data)
        if data[CAN_CHECKSUM_BYTE] != expected:
            raise ChecksumError(
                f"{message.name}: checksum 0x{data[CAN_CHECKSUM_BYTE]:02X}, expected 0x{expected:02X}"
            )
        try:
            values = message.decode(bytes(data), decode_choices=False, scaling=False)
        except cantools.database.DecodeError as err:
            raise FrameError(f"{message.name}: {err}") from err
        return DecodedFrame(message.name, {k: int(v) for k, v in values.items()})


@dataclass
class FrameStats:
    """Receive-side bookkeeping of the driver (counts since the driver started)."""

    rx_frames: int = 0
    checksum_errors: int = 0
    invalid_frames: int = 0
    """Wrong length or a field value outside its code table."""
    unknown_ids: int = 0
    repeated: int = 0
    lost: int = 0
    incomplete_cycles: int = 0
    transport_errors: int = 0
    tx_frames: int = 0
    reopens: int = 0
    """Times the CAN interface was opened again after it kept failing (an adapter unplugged and back)."""
