"""CAN frame fault injection for the simulated controller: drop, corrupt, repeat, delay frames; silences; link gaps.

``CanFaultInjector`` decides per frame (seeded rates and one-shot rules); ``FrameOutbox`` holds the frames it
delays until they are due. Both CAN servers (``slcan_server.py``, ``can_bus_server.py``) use them.
"""

from __future__ import annotations

import heapq
import itertools
import random
import threading
from collections import Counter
from dataclasses import dataclass
from typing import Literal

from sim_devices.controller.can_peer import Frame
from sim_devices.controller.link_gaps import LinkGaps
from sim_devices.controller.state_machine import CanFaultConfig

Direction = Literal["tx", "rx"]


@dataclass
class _Rule:
    action: Literal["drop", "corrupt", "repeat", "delay"]
    direction: Direction
    frame_id: int | None
    remaining: int
    delay_s: float = 0.0


class CanFaultInjector:
    """Frame-level faults, switchable at start (CanFaultConfig) and at run time (the methods); thread-safe.

    "tx" frames are sent by the controller, "rx" frames are received by it. Rates apply to both directions,
    the constant delay to tx frames only; one-shot rules consume one count per matching frame.
    """

    def __init__(self, config: CanFaultConfig | None = None) -> None:
        cfg = config or CanFaultConfig()
        self._rng = random.Random(cfg.seed)
        self._lock = threading.Lock()
        self.drop_rate = cfg.drop_rate
        self.corrupt_rate = cfg.corrupt_rate
        self.repeat_rate = cfg.repeat_rate
        self.delay_s = cfg.delay_s
        self.heartbeat = cfg.heartbeat
        self.gaps = LinkGaps(cfg.gaps_per_min, cfg.gap_min_s, cfg.gap_max_s, cfg.seed, cfg.gap_log, cfg.max_gaps,
                             cfg.gap_at_frames)
        self._rules: list[_Rule] = []
        self.applied: Counter[str] = Counter()

    def _add(self, rule: _Rule) -> None:
        with self._lock:
            self._rules.append(rule)

    def drop_next(self, count: int = 1, *, frame_id: int | None = None, direction: Direction = "tx") -> None:
        self._add(_Rule("drop", direction, frame_id, count))

    def corrupt_next(self, count: int = 1, *, frame_id: int | None = None, direction: Direction = "tx") -> None:
        """Flip one (seeded random) bit of the next matching frames."""
        self._add(_Rule("corrupt", direction, frame_id, count))

    def repeat_next(self, count: int = 1, *, frame_id: int | None = None, direction: Direction = "tx") -> None:
        self._add(_Rule("repeat", direction, frame_id, count))

    def delay_next(self, delay_s: float, count: int = 1, *, frame_id: int | None = None) -> None:
        """Hold back the next matching controller frames (later frames overtake them)."""
        self._add(_Rule("delay", "tx", frame_id, count, delay_s))

    def set_heartbeat(self, enabled: bool) -> None:
        """False: the controller stops sending Status/Feedback (a lost heartbeat)."""
        self.heartbeat = enabled

    def clear(self) -> None:
        """Remove all one-shot rules and rates (the heartbeat switch is left as it is)."""
        with self._lock:
            self._rules.clear()
            self.drop_rate = self.corrupt_rate = self.repeat_rate = self.delay_s = 0.0

    def _take(self, action: str, direction: Direction, frame_id: int) -> _Rule | None:
        for rule in self._rules:
            if rule.action == action and rule.direction == direction and rule.frame_id in (None, frame_id):
                rule.remaining -= 1
                if rule.remaining <= 0:
                    self._rules.remove(rule)
                return rule
        return None

    def apply(self, direction: Direction, frame_id: int, data: bytes) -> list[tuple[float, bytes]]:
        """The copies of a frame that actually go through, each with its extra delay in seconds.

        In a link gap nothing the controller sends goes out; what it receives is kept and recorded.
        """
        if direction == "rx":
            self.gaps.count_received()
        into_gap = self.gaps.in_gap()
        if into_gap is not None:
            if direction == "tx":
                self.applied["gap_drop"] += 1
                return []
            self.gaps.note_received(frame_id, into_gap)
        with self._lock:
            if self._take("drop", direction, frame_id) or self._rng.random() < self.drop_rate:
                self.applied["drop"] += 1
                return []
            if data and (self._take("corrupt", direction, frame_id) or self._rng.random() < self.corrupt_rate):
                self.applied["corrupt"] += 1
                bit = self._rng.randrange(8 * len(data))
                mutable = bytearray(data)
                mutable[bit // 8] ^= 1 << (bit % 8)
                data = bytes(mutable)
            delay = self.delay_s if direction == "tx" else 0.0
            rule = self._take("delay", direction, frame_id)
            if rule is not None:
                self.applied["delay"] += 1
                delay += rule.delay_s
            copies = [(delay, data)]
            if self._take("repeat", direction, frame_id) or self._rng.random() < self.repeat_rate:
                self.applied["repeat"] += 1
                copies.append((delay, data))
            return copies


class FrameOutbox:
    """Frames to send now or later (fault-injected delays), ordered by due time."""

    def __init__(self, faults: CanFaultInjector) -> None:
        self.faults = faults
        self._heap: list[tuple[float, int, int, bytes]] = []
        self._seq = itertools.count()

    def schedule(self, frames: list[Frame], now: float) -> list[Frame]:
        """Apply tx faults; return the frames due now and keep the delayed ones."""
        immediate = []
        for frame_id, data in frames:
            for delay, copy in self.faults.apply("tx", frame_id, data):
                if delay > 0:
                    heapq.heappush(self._heap, (now + delay, next(self._seq), frame_id, copy))
                else:
                    immediate.append((frame_id, copy))
        return immediate

    def due(self, now: float) -> list[Frame]:
        out = []
        while self._heap and self._heap[0][0] <= now:
            _, _, frame_id, data = heapq.heappop(self._heap)
            out.append((frame_id, data))
        return out

    def next_due(self) -> float | None:
        return self._heap[0][0] if self._heap else None

    def clear(self) -> None:
        self._heap.clear()
