"""Hand-written CAN frames of the controller protocol (from docs/protocols.md) and small helpers for its tests.

Independent of the code under test: byte layouts, frame IDs and the CRC-8 are written out here from the docs.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.protocols.controller_states import ControllerState, RefusalReason
from hilcal.robot import Robot

HEARTBEAT_TIMEOUT_S = 0.3
ID_ESTOP, ID_FAULT_EVENT, ID_COMMAND, ID_ACK = 0x010, 0x020, 0x100, 0x101
ID_SETPOINT = (0x110, 0x111, 0x112)
ID_STATUS = 0x180
ID_FEEDBACK = (0x190, 0x191, 0x192)
S = ControllerState
R = RefusalReason


# ------------------------------------------------------------------ independent frame helpers (from the docs)


def crc8_bitwise(data: bytes) -> int:
    """CRC-8/SAE-J1850 written out bit by bit: poly 0x1D, init 0xFF, xorout 0xFF."""
    crc = 0xFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ 0xFF


def seal(frame_id: int, payload7: bytes) -> bytes:
    """Append the checksum byte: CRC over [ID high, ID low, bytes 0..6]."""
    assert len(payload7) == 7
    return payload7 + bytes([crc8_bitwise(bytes([frame_id >> 8, frame_id & 0xFF]) + payload7)])


def le24(value: int) -> bytes:
    return value.to_bytes(3, "little")


def command_frame(code: int, counter: int) -> bytes:
    return seal(ID_COMMAND, bytes([code, 0, 0, 0, 0, 0, counter]))


def setpoint_frames(lengths_mm: np.ndarray, counter: int) -> list[tuple[int, bytes]]:
    um = [round(v * 1000) for v in lengths_mm]
    return [(ID_SETPOINT[k], seal(ID_SETPOINT[k], le24(um[2 * k]) + le24(um[2 * k + 1]) + bytes([counter])))
            for k in range(3)]


@dataclass
class Ack:
    command: int
    reason: int
    state: int
    request_counter: int


def parse_ack(data: bytes) -> Ack:
    return Ack(data[0], data[1], data[2] & 0x0F, data[2] >> 4)


def wait_until(predicate: Callable[[], bool], timeout_s: float = 2.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.005)


def ik(robot: Robot, pose: list[float]) -> np.ndarray:
    return inverse_kinematics(Geometry.nominal(robot), np.asarray(pose, dtype=float))
