"""Link gaps of the simulated controller: at random times no frame leaves it for 0.05-0.5 s (a short drop-out).

Gaps start as a seeded Poisson process (``gaps_per_min``) with uniform lengths, up to ``max_gaps``. Every
gap, and every frame the controller receives while one lasts (with how far into the gap it arrived), goes to
an optional JSONL file, so a soak test can prove that the host sent no motion command once it could know the
link was down; the file also carries the gap count across a restart of the simulator.
"""

from __future__ import annotations

import json
import random
import threading
import time
from pathlib import Path


class LinkGaps:
    """Decides whether a frame falls in a gap (real time) and keeps the record; thread-safe."""

    def __init__(self, per_min: float, min_s: float, max_s: float, seed: int, log_path: str | None = None,
                 max_gaps: int | None = None, at_frames: list[int] | tuple[int, ...] = ()) -> None:
        self.per_min = per_min
        self.min_s = min_s
        self.max_s = max_s
        self._rng = random.Random(seed + 7919)
        self._lock = threading.Lock()
        self._log = Path(log_path) if log_path else None
        self._start: float | None = None
        self._end = 0.0
        self._next: float | None = None
        self.max_gaps = max_gaps
        self.at_frames = set(at_frames)
        self.received = 0
        self.count = 0
        if self._log is not None and self._log.is_file():
            self.count = sum('"event": "gap"' in line for line in self._log.read_text().splitlines())
        self.received_in_gap: list[dict] = []

    def _write(self, record: dict) -> None:
        if self._log is not None:
            with self._log.open("a") as f:
                f.write(json.dumps(record) + "\n")

    def _begin(self, start: float, why: str) -> None:
        if self.max_gaps is not None and self.count >= self.max_gaps:
            return
        self._start = start
        self._end = start + self._rng.uniform(self.min_s, self.max_s)
        self.count += 1
        self._write({"event": "gap", "start_s": start, "length_s": self._end - start, "why": why,
                     "wall_time": time.time()})

    def _advance(self, now: float) -> None:
        if self.per_min <= 0:
            return
        if self._next is None:
            self._next = now + self._rng.expovariate(self.per_min / 60.0)
        if now >= self._next and now >= self._end:
            self._begin(self._next, "random")
            self._next = max(self._end, self._next) + self._rng.expovariate(self.per_min / 60.0)

    def count_received(self) -> None:
        """One more frame reached the controller; a gap starts now if this count is in ``at_frames``."""
        with self._lock:
            self.received += 1
            now = time.monotonic()
            if self.received in self.at_frames and now >= self._end:
                self._begin(now, f"frame {self.received}")

    def in_gap(self, now: float | None = None) -> float | None:
        """Seconds since the current gap began, or None outside a gap."""
        now = time.monotonic() if now is None else now
        with self._lock:
            self._advance(now)
            if self._start is not None and self._start <= now < self._end:
                return now - self._start
            return None

    def note_received(self, frame_id: int, into_gap_s: float) -> None:
        """A frame reached the controller `into_gap_s` after the gap began (the host had not noticed yet)."""
        record = {"event": "received_in_gap", "frame_id": frame_id, "into_gap_s": into_gap_s,
                  "wall_time": time.time()}
        with self._lock:
            self.received_in_gap.append(record)
            self._write(record)
