"""The panel's live state: named sections (a snapshot) plus a numbered stream of changes to them.

Writers (the engine observer, the operator control, the station monitor) run in their own threads; readers
are browsers on the web server's event loop. A browser first gets the snapshot and then every later change
in order, so a page reload or a second browser shows exactly the same state. Each change carries the wall
time it was made (`t`, seconds since the epoch), which lets a browser measure the delivery latency.
"""

from __future__ import annotations

import asyncio
import copy
import json
import threading
import time
from typing import Any

import numpy as np

MAX_LIST = 400
"""Longest list section kept (the timeline); measurements are bounded by the plan instead."""

SECTIONS: dict[str, Any] = {
    "run": {"mode": "idle", "status": "idle"},
    "plan": None,
    "progress": None,
    "controller": None,
    "cmm": {"session": "closed"},
    "measurements": [],
    "prompt": None,
    "identification": None,
    "upload": None,
    "result": None,
    "diagnosis": None,
    "adaptive": None,
    "timeline": [],
}


def plain(value: Any) -> Any:
    """A JSON-ready copy: numpy arrays and scalars become lists and floats, non-finite floats None."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.generic):
        return plain(value.item())
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


class LiveState:
    """Thread-safe sections with change listeners; `close()` ends every listener's stream."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._sections: dict[str, Any] = copy.deepcopy(SECTIONS)
        self._seq = 0
        self._listeners: set[tuple[asyncio.AbstractEventLoop, asyncio.Queue[str | None]]] = set()
        self._closed = False

    def get(self, section: str) -> Any:
        with self._lock:
            return copy.deepcopy(self._sections[section])

    def set(self, section: str, value: Any) -> None:
        """Replace a section."""
        self._change(section, "set", plain(value))

    def update(self, section: str, **fields: Any) -> None:
        """Merge fields into a dict section (created if None) and publish the whole section."""
        with self._lock:
            current = dict(self._sections.get(section) or {})
            current.update(plain(fields))
            self._publish_locked(section, "set", current)

    def append(self, section: str, item: Any) -> None:
        """Add an item to a list section."""
        self._change(section, "append", plain(item))

    def _change(self, section: str, op: str, value: Any) -> None:
        with self._lock:
            self._publish_locked(section, op, value)

    def _publish_locked(self, section: str, op: str, value: Any) -> None:
        if section not in self._sections:
            raise KeyError(f"unknown panel section {section!r}")
        if op == "set":
            self._sections[section] = value
        else:
            items = self._sections[section]
            items.append(value)
            if section != "measurements" and len(items) > MAX_LIST:
                del items[: len(items) - MAX_LIST]
        self._seq += 1
        text = json.dumps({"seq": self._seq, "t": time.time(), "section": section, "op": op, "value": value})
        for loop, queue in list(self._listeners):
            _deliver(loop, queue, text)

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            return {"seq": self._seq, "t": time.time(), "sections": copy.deepcopy(self._sections)}

    def subscribe(self) -> tuple[str, asyncio.Queue[str | None]]:
        """Called on the event loop: the snapshot (JSON) and a queue of every later change (None: closed)."""
        queue: asyncio.Queue[str | None] = asyncio.Queue()
        loop = asyncio.get_running_loop()
        with self._lock:
            snap = json.dumps({"seq": self._seq, "t": time.time(), "sections": self._sections})
            if self._closed:
                queue.put_nowait(None)
            else:
                self._listeners.add((loop, queue))
        return snap, queue

    def unsubscribe(self, queue: asyncio.Queue[str | None]) -> None:
        with self._lock:
            self._listeners = {entry for entry in self._listeners if entry[1] is not queue}

    def note(self, text: str, level: str = "info") -> None:
        """Add a line to the timeline (what happened, newest last; bounded)."""
        self.append("timeline", {"t": time.time(), "text": text, "level": level})

    @property
    def listeners(self) -> int:
        with self._lock:
            return len(self._listeners)

    def close(self) -> None:
        """End every stream (the web server can then shut down without waiting for browsers)."""
        with self._lock:
            self._closed = True
            listeners, self._listeners = self._listeners, set()
        for loop, queue in listeners:
            _deliver(loop, queue, None)


def _deliver(loop: asyncio.AbstractEventLoop, queue: asyncio.Queue[str | None], item: str | None) -> None:
    try:
        loop.call_soon_threadsafe(queue.put_nowait, item)
    except RuntimeError:
        pass  # that browser's event loop is already closed

