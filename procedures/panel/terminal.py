"""Lines typed at the terminal, for questions that the page can answer too.

A daemon thread polls the raw file descriptor with select (no Python-level buffer is held, so it never
blocks the interpreter's shutdown) and hands each complete line to a callback. End of input just ends the
thread: the page can still answer.
"""

from __future__ import annotations

import os
import select
import threading
from collections.abc import Callable


class TerminalInput:
    """Reads lines from `fd` (default: standard input) in a background thread until `stop()` or end of input."""

    def __init__(self, on_line: Callable[[str], None], fd: int = 0, poll_s: float = 0.2) -> None:
        self.on_line = on_line
        self.fd = fd
        self.poll_s = poll_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="panel-terminal-input", daemon=True)

    def start(self) -> TerminalInput:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2 * self.poll_s + 1.0)

    def _loop(self) -> None:
        pending = b""
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self.fd], [], [], self.poll_s)
                if not ready:
                    continue
                chunk = os.read(self.fd, 4096)
            except (OSError, ValueError):
                return
            if not chunk:
                return
            pending += chunk
            while b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                self.on_line(line.decode("utf-8", "replace"))
