"""Opening the CAN interface: ``can.Bus(**config)``, except that an SLCAN adapter reads its port in chunks.

python-can's ``slcan`` interface reads the serial port one byte per system call (a select and a read each): a
heartbeat cycle of four frames is about 120 bytes, so the driver's reader thread spent about a millisecond per
cycle in system calls and held the interpreter lock in between, which delayed every acknowledgement and the
command thread's own I/O. ``ChunkedSlcanBus`` is the same interface reading what the port holds in one call;
what it returns (one line per call, ``\\r``- or ``\\a``-terminated) and its timeouts are unchanged. Its
``send_batch`` writes several frames at once (a leg setpoint is three frames): one write and one wake-up of the
adapter instead of three.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import can
import serial
from can.exceptions import error_check
from can.interfaces.slcan import slcanBus
from can.util import load_config


class ChunkedSlcanBus(slcanBus):
    """python-can's slcan bus reading every byte the port holds at once instead of one byte per call."""

    _TERMINATORS = (slcanBus._OK[0], slcanBus._ERROR[0])

    def _take_line(self) -> str | None:
        """The first complete line in the buffer (with its terminator), removed from it; None if there is none."""
        ends = [i for i in (self._buffer.find(t) for t in self._TERMINATORS) if i >= 0]
        if not ends:
            return None
        end = min(ends) + 1
        line = self._buffer[:end].decode()
        del self._buffer[:end]
        return line

    def _read(self, timeout: float | None) -> str | None:
        """The next line, or None once ``timeout`` has passed (checked after every read, as python-can does)."""
        expiry = serial.Timeout(timeout)
        port = self.serialPortOrig
        with error_check("Could not read from serial device"):
            line = self._take_line()
            while line is None:
                chunk = port.read(1)  # waits at most the port's read timeout
                if chunk:
                    waiting = port.in_waiting
                    self._buffer.extend(chunk + port.read(waiting) if waiting else chunk)
                    line = self._take_line()
                if line is None and expiry.expired():
                    return None
            return line

    def send_batch(self, msgs: Sequence[can.Message], timeout: float | None = None) -> None:
        """The frames in order, in one write (the same lines as ``send``, one after the other)."""
        if any(msg.is_remote_frame or msg.is_fd or msg.is_extended_id for msg in msgs):
            for msg in msgs:
                self.send(msg, timeout)
            return
        if timeout != self.serialPortOrig.write_timeout:
            self.serialPortOrig.write_timeout = timeout
        self._write(self.LINE_TERMINATOR.decode().join(
            f"t{msg.arbitration_id:03X}{msg.dlc:d}{bytes(msg.data).hex().upper()}" for msg in msgs))


def open_bus(config: dict[str, Any]) -> can.BusABC:
    """``can.Bus(**config)`` (configuration files and environment included); slcan as ``ChunkedSlcanBus``."""
    if config.get("interface") != "slcan":
        return can.Bus(**config)
    kwargs = dict(load_config(config=dict(config)))
    kwargs.pop("interface", None)
    channel = kwargs.pop("channel", None)
    return ChunkedSlcanBus(channel, **kwargs)
