"""Fault injection for the simulated tracker: seeded per-command rates plus one-shot injections, drawn per command,
and a hang (silence from some command on).

Faults: unknown packets before the answer, a cut answer, silence, a late answer, a beam break during a measurement
(see ``sim_devices.tracker.config.Fault``).
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from hilcal.protocols.emscon import HEADER, DataType
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


NO_FAULTS = FaultPlan()


class FaultInjector:
    """Seeded fault rates plus one-shot injections; thread-safe, changeable while the server runs."""

    def __init__(self, rates: FaultRates, seed: int, hang_after: int | None = None) -> None:
        self._lock = threading.Lock()
        self._rates = rates
        self._hang_after = hang_after
        self._drawn = 0
        self._pending: Counter[tuple[Fault, str | None]] = Counter()
        self._rng = np.random.default_rng([seed, 0x7AC])
        self.applied: Counter[Fault] = Counter()
        """How often each fault has been applied so far."""

    def set_rates(self, rates: FaultRates | Mapping[str, float]) -> None:
        """Replace the per-command fault probabilities."""
        with self._lock:
            self._rates = rates if isinstance(rates, FaultRates) else FaultRates.model_validate(dict(rates))

    def inject(self, fault: Fault | str, count: int = 1, command: str | None = None) -> None:
        """Apply ``fault`` to the next ``count`` eligible commands (only commands named ``command``, e.g.
        ``"GoPosition"``, if given)."""
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
            self._drawn += 1
            if self._hang_after is not None and self._drawn > self._hang_after:
                self.applied[Fault.SILENCE] += 1
                return FaultPlan(silence=True)
            if not any(self._pending.values()) and not any(getattr(self._rates, f.value) for f in Fault):
                return NO_FAULTS
            chosen: dict[Fault, bool] = {}
            for fault in Fault:
                if fault is Fault.BEAM_BREAK and command != "StartMeasurement":
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

