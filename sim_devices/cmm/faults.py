"""Fault injection for the simulated CMM: seeded per-command rates plus one-shot injections, drawn per command.

Faults: garbage lines, a cut line, silence, probe miss, outlier (see ``cmm_config.Fault``).
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from hilcal.protocols.cmm import TERMINATOR, Command
from sim_devices.cmm.config import Fault, FaultRates


@dataclass(frozen=True)
class FaultPlan:
    """The faults applied to one command."""

    garbage: bool = False
    partial: bool = False
    silence: bool = False
    miss: bool = False
    outlier: bool = False


NO_FAULTS = FaultPlan()


class FaultInjector:
    """Seeded fault rates plus one-shot injections; thread-safe, changeable while the server runs."""

    def __init__(self, rates: FaultRates, seed: int) -> None:
        self._lock = threading.Lock()
        self._rates = rates
        self._pending: Counter[tuple[Fault, str | None]] = Counter()
        self._rng = np.random.default_rng([seed, 0xFA17])
        self.applied: Counter[Fault] = Counter()
        """How often each fault has been applied so far."""

    def set_rates(self, rates: FaultRates | Mapping[str, float]) -> None:
        """Replace the per-command fault probabilities."""
        with self._lock:
            self._rates = rates if isinstance(rates, FaultRates) else FaultRates.model_validate(dict(rates))

    def inject(self, fault: Fault | str, count: int = 1, command: str | None = None) -> None:
        """Apply ``fault`` to the next ``count`` eligible commands (only commands named ``command`` if given)."""
        with self._lock:
            self._pending[(Fault(fault), command)] += count

    def pending(self) -> int:
        """One-shot injections not yet applied."""
        with self._lock:
            return sum(self._pending.values())

    def clear(self) -> None:
        """No more faults: zero rates, no pending injections."""
        with self._lock:
            self._rates = FaultRates()
            self._pending.clear()

    def draw(self, command: str) -> FaultPlan:
        """Decide the faults of the next command (no rates and nothing pending: none, drawing no random number)."""
        with self._lock:
            if not any(self._pending.values()) and not any(getattr(self._rates, f.value) for f in Fault):
                return NO_FAULTS
            chosen = {}
            for fault in Fault:
                if fault in (Fault.MISS, Fault.OUTLIER) and command != Command.PT_MEAS:
                    chosen[fault] = False
                    continue
                hit = False
                for key in ((fault, command), (fault, None)):
                    if self._pending[key] > 0:
                        self._pending[key] -= 1
                        hit = True
                        break
                rate = getattr(self._rates, fault.value)
                if rate > 0 and self._rng.random() < rate:
                    hit = True
                chosen[fault] = hit
            if chosen[Fault.SILENCE]:
                chosen = {f: f is Fault.SILENCE for f in Fault}
            for fault, hit in chosen.items():
                if hit:
                    self.applied[fault] += 1
            return FaultPlan(**{f.value: hit for f, hit in chosen.items()})

    def garbage_line(self) -> bytes:
        """A random line that is not a protocol line (its first byte is never a digit)."""
        with self._lock:
            n = int(self._rng.integers(1, 60))
            body = self._rng.integers(0, 256, n).astype(np.uint8)
            first = int(self._rng.integers(0x3A, 0x100))
        body = bytes(b for b in body.tobytes() if b not in (0x0A, 0x0D))
        return bytes([first if first not in (0x0A, 0x0D) else 0x7E]) + body + TERMINATOR
