"""Fault injection for the simulated CMM: seeded per-command rates plus one-shot injections, drawn per command.

Faults: garbage lines, a cut line, silence, probe miss, outlier (see ``config.Fault``); drawn per received command
by the method it names (``""`` for a line that could not be read).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hilcal.protocols.ippdme import TERMINATOR, Method
from sim_devices.cmm.config import Fault, FaultRates
from sim_devices.command_faults import CommandFaults


@dataclass(frozen=True)
class FaultPlan:
    """The faults applied to one command."""

    garbage: bool = False
    partial: bool = False
    silence: bool = False
    miss: bool = False
    outlier: bool = False


class FaultInjector(CommandFaults):
    """Seeded fault rates plus one-shot injections; thread-safe, changeable while the server runs."""

    fault_type = Fault
    rates_type = FaultRates
    plan_type = FaultPlan

    def __init__(self, rates: FaultRates, seed: int) -> None:
        super().__init__(rates, seed, 0xFA17)

    def eligible(self, fault: Fault, command: str) -> bool:
        """A probe miss and an outlier only on a touch."""
        return fault not in (Fault.MISS, Fault.OUTLIER) or command == Method.PT_MEAS

    def garbage_line(self) -> bytes:
        """A random line that is not a protocol line (its first byte is neither a digit nor E)."""
        with self._lock:
            n = int(self._rng.integers(1, 60))
            body = self._rng.integers(0, 256, n).astype(np.uint8)
            first = int(self._rng.integers(0x3A, 0x100))
        body = bytes(b for b in body.tobytes() if b not in (0x0A, 0x0D))
        return bytes([first if first not in (0x0A, 0x0D, 0x45) else 0x7E]) + body + TERMINATOR
