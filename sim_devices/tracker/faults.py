"""Fault injection for the simulated tracker: seeded per-command rates plus one-shot injections, drawn per command,
and a hang (silence from some command on).

Faults: unknown packets before the answer, a cut answer, silence, a late answer, a beam break during a measurement
(see ``sim_devices.tracker.config.Fault``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hilcal.protocols.emscon import HEADER, DataType
from sim_devices.command_faults import CommandFaults
from sim_devices.tracker.config import Fault, FaultRates

GARBAGE_TYPE_BASE = 1000
"""Data types from here up are not in the AT4xx definitions (a newer server's packets)."""


@dataclass(frozen=True)
class FaultPlan:
    """The faults applied to one command."""

    garbage: bool = False
    partial: bool = False
    silence: bool = False
    delay: bool = False
    beam_break: bool = False




class FaultInjector(CommandFaults):
    """Seeded fault rates plus one-shot injections and a hang; thread-safe, changeable while the server runs."""

    fault_type = Fault
    rates_type = FaultRates
    plan_type = FaultPlan

    def __init__(self, rates: FaultRates, seed: int, hang_after: int | None = None) -> None:
        super().__init__(rates, seed, 0x7AC)
        self._hang_after = hang_after
        self._drawn = 0

    def eligible(self, fault: Fault, command: str) -> bool:
        """A beam break only during a measurement."""
        return fault is not Fault.BEAM_BREAK or command == "StartMeasurement"

    def draw(self, command: str) -> FaultPlan:
        """Decide the faults of the next command: silence for good once the hang's command count is passed."""
        with self._lock:
            self._drawn += 1
            if self._hang_after is not None and self._drawn > self._hang_after:
                self.applied[Fault.SILENCE] += 1
                return FaultPlan(silence=True)
            return self._draw_locked(command)

    def garbage_packet(self) -> bytes:
        """A well-framed packet of a data type the AT4xx definitions lack, with a random body."""
        with self._lock:
            n = int(self._rng.integers(4, 60))
            data_type = GARBAGE_TYPE_BASE + int(self._rng.integers(0, 1000))
            body = self._rng.integers(0, 256, n).astype(np.uint8).tobytes()
        assert data_type not in DataType._value2member_map_
        return HEADER.pack(HEADER.size + n, data_type) + body


def cut(data: bytes) -> bytes:
    """The first half of an answer (at least a header's worth, so the receiver waits for the rest)."""
    keep = max(HEADER.size + 1, len(data) // 2)
    return data[: min(keep, len(data) - 1)]

