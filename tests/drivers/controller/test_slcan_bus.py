"""The chunked SLCAN interface: the same frames, lines and timeouts as python-can's slcan, fewer system calls.

Runs on pyserial's ``loop://`` port, where every byte written comes back as input.
"""

from __future__ import annotations

import time

import can
import pytest
from can.interfaces.slcan import slcanBus

from drivers.controller.slcan_bus import ChunkedSlcanBus, open_bus


@pytest.fixture
def bus():
    b = ChunkedSlcanBus("loop://", sleep_after_open=0, timeout=0.01)
    b.flush()  # the "O" that opened the channel came back
    yield b
    b.shutdown()


def test_frames_split_across_reads_and_mixed_with_replies(bus):
    port = bus.serialPortOrig
    port.write(b"z\rt1232AABB\r\at12")
    first = bus.recv(timeout=0.5)
    assert first is not None and first.arbitration_id == 0x123 and bytes(first.data) == b"\xaa\xbb"
    assert bus.recv(timeout=0.05) is None  # "\a" is no frame and "t12" is not a whole line yet
    port.write(b"31CC\r")
    second = bus.recv(timeout=0.5)
    assert second is not None and second.arbitration_id == 0x123 and bytes(second.data) == b"\xcc"


def test_a_line_that_never_ends_does_not_hold_the_reader(bus):
    bus.serialPortOrig.write(b"t123" + b"A" * 4000)
    t0 = time.monotonic()
    assert bus.recv(timeout=0.1) is None
    assert time.monotonic() - t0 < 1.0


def test_send_batch_writes_what_send_writes(bus):
    msgs = [can.Message(arbitration_id=0x100 + k, data=bytes([k, 0xAB, 0x0C]), is_extended_id=False)
            for k in range(3)]
    for msg in msgs:
        bus.send(msg, timeout=0.1)
    one_by_one = bus.serialPortOrig.read(bus.serialPortOrig.in_waiting)
    bus.send_batch(msgs, timeout=0.1)
    batched = bus.serialPortOrig.read(bus.serialPortOrig.in_waiting)
    assert batched == one_by_one == b"t100300AB0C\rt101301AB0C\rt102302AB0C\r"


def test_open_bus_chooses_the_chunked_slcan_only_for_slcan():
    slcan = open_bus({"interface": "slcan", "channel": "loop://", "sleep_after_open": 0})
    virtual = open_bus({"interface": "virtual", "channel": "hilcal-test-open-bus"})
    try:
        assert isinstance(slcan, ChunkedSlcanBus) and isinstance(slcan, slcanBus)
        assert not isinstance(virtual, slcanBus)
    finally:
        slcan.shutdown()
        virtual.shutdown()
