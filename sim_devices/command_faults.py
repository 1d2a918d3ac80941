"""Per-command fault draws shared by the simulated devices' servers: seeded rates plus one-shot injections.

Each device names its faults (an enum whose values are the rates' and the plan's field names), the rates (a pydantic
model), the plan of one command (a frozen dataclass of booleans) and which faults a command can get; this draws them,
thread-safe and changeable while the server runs. A silence replaces every other fault of its command.
"""

from __future__ import annotations

import threading
from collections import Counter
from collections.abc import Mapping
from enum import StrEnum
from typing import Any

import numpy as np

SILENCE = "silence"


class CommandFaults:
    """Seeded fault rates plus one-shot injections for a device's commands (subclass: the device's kinds)."""

    fault_type: type[StrEnum]
    rates_type: Any
    plan_type: Any

    def __init__(self, rates: Any, seed: int, salt: int) -> None:
        self._lock = threading.Lock()
        self._rates = rates
        self._pending: Counter[tuple[Any, str | None]] = Counter()
        self._rng = np.random.default_rng([seed, salt])
        self.applied: Counter[Any] = Counter()
        """How often each fault has been applied so far."""

    def eligible(self, fault: Any, command: str) -> bool:
        """Whether this command can get this fault (a probe miss only on a touch, say)."""
        return True

    def set_rates(self, rates: Any | Mapping[str, float]) -> None:
        """Replace the per-command fault probabilities."""
        with self._lock:
            self._rates = rates if isinstance(rates, self.rates_type) else self.rates_type.model_validate(dict(rates))

    def inject(self, fault: Any, count: int = 1, command: str | None = None) -> None:
        """Apply ``fault`` to the next ``count`` eligible commands (only commands named ``command`` if given)."""
        with self._lock:
            self._pending[(self.fault_type(fault), command)] += count

    def pending(self) -> int:
        """One-shot injections not yet applied."""
        with self._lock:
            return sum(self._pending.values())

    def clear(self) -> None:
        """No more faults: zero rates, no pending injections."""
        with self._lock:
            self._rates = self.rates_type()
            self._pending.clear()

    def draw(self, command: str) -> Any:
        """Decide the faults of the next command (no rates and nothing pending: none, drawing no random number)."""
        with self._lock:
            return self._draw_locked(command)

    def _draw_locked(self, command: str) -> Any:
        faults = list(self.fault_type)
        if not any(self._pending.values()) and not any(getattr(self._rates, f.value) for f in faults):
            return self.plan_type()
        chosen: dict[Any, bool] = {}
        for fault in faults:
            if not self.eligible(fault, command):
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
        silence = self.fault_type(SILENCE)
        if chosen[silence]:
            chosen = {f: f is silence for f in faults}
        for fault, hit in chosen.items():
            if hit:
                self.applied[fault] += 1
        return self.plan_type(**{f.value: hit for f, hit in chosen.items()})
