"""The CANopen link of a controller: ``canopen``'s ``Network`` on a python-can bus, one ``RemoteNode`` per node
with its dictionary from the EDS/DCF, typed SDO reads and writes of resolved slots, the heartbeat as the link's
liveness and the emergency messages the nodes send.

SDO requests are never retried (``MAX_RETRIES = 1``: a write whose answer was lost may have been executed; the
caller decides). The heartbeat consumer (CiA 301 v4.2.0 §7.2.8.3.2.1) counts a node lost once its heartbeat is older
than the consumer time; a boot-up message (state 0) says the node restarted and lost whatever it was told.
"""

from __future__ import annotations

import contextlib
import struct
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import canopen
import structlog
from canopen.objectdictionary import ObjectDictionary

from drivers.controller.canopen_codes import emcy_text, error_register_text, sdo_abort_text
from drivers.controller.canopen_mapping import Slot
from drivers.controller.slcan_bus import open_bus

log = structlog.get_logger(__name__)

HEARTBEAT_OBJECT = (0x1017, 0)
"""Producer heartbeat time, ms (CiA 301 v4.2.0 §7.5.2.18)."""
HEARTBEAT_FACTOR = 2.5
"""A node is lost once its heartbeat is this many producer periods old (and at least the station's timeout)."""
SLCAN_READ_TIMEOUT_S = 0.02
NOTIFIER_CYCLE_S = 0.05
"""The bus reader's receive timeout: how long closing the link waits for it (canopen's default is 1 s)."""
NMT_STATES = {0: "BOOT-UP", 4: "STOPPED", 5: "OPERATIONAL", 127: "PRE-OPERATIONAL"}


class SdoFailure(Exception):
    """An SDO request that failed: ``code`` the abort code (None: no answer in time, or the bus failed)."""

    def __init__(self, message: str, code: int | None) -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class Emergency:
    """One EMCY message: node, error code, error register, manufacturer bytes, when (monotonic s)."""

    node: int
    code: int
    register: int
    data: bytes
    at_s: float

    def text(self, vendor: Mapping[int, str] | None = None) -> str:
        return (f"node {self.node}: EMCY {emcy_text(self.code, vendor)}, error register "
                f"{error_register_text(self.register)}")


def load_dictionaries(eds: str | Path | Mapping[int, str | Path], nodes: Sequence[int]) -> dict[int, ObjectDictionary]:
    """Each node's dictionary from its EDS/DCF (one file for all, or one per node); ValueError naming the file."""
    out = {}
    for node in nodes:
        path = eds[node] if isinstance(eds, Mapping) else eds
        try:
            out[node] = canopen.import_od(str(path), node)
        except (OSError, ValueError, KeyError) as err:
            raise ValueError(f"cannot read the EDS/DCF {path}: {err}") from err
        except Exception as err:  # configparser errors of a malformed file
            raise ValueError(f"cannot read the EDS/DCF {path}: {type(err).__name__}: {err}") from err
    return out


class CanopenLink:
    """The bus and the nodes of one controller (see the module docstring); a context manager."""

    def __init__(self, bus_config: dict[str, Any], dictionaries: Mapping[int, ObjectDictionary], *,
                 sdo_timeout_s: float = 0.5, heartbeat_timeout_s: float = 0.1, heartbeat_ms: int | None = None,
                 bus: Any = None, writes: bool = True) -> None:
        self.nodes = list(dictionaries)
        self.sdo_timeout_s = sdo_timeout_s
        self.heartbeat_timeout_s = heartbeat_timeout_s
        config = dict(bus_config)
        if config.get("interface") == "slcan":
            config.setdefault("timeout", SLCAN_READ_TIMEOUT_S)
        self.endpoint = (f"canopen://{config.get('interface')}/{config.get('channel')}"
                         f"#{','.join(str(n) for n in self.nodes)}")
        self._cond = threading.Condition()
        self._locks = {n: threading.Lock() for n in self.nodes}
        self._heard: dict[int, float] = {}
        self._nmt: dict[int, int] = {}
        self.boots: dict[int, int] = dict.fromkeys(self.nodes, 0)
        self.emergencies: list[Emergency] = []
        self._closed = False
        self.network = canopen.Network(bus if bus is not None else open_bus(config))
        self.network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
        self.network.connect()
        self.remote: dict[int, canopen.RemoteNode] = {}
        self.heartbeats_found: dict[int, int] = {}
        """Each node's producer heartbeat time (ms) before this link set it; put back at close."""
        try:
            for n, od in dictionaries.items():
                node = canopen.RemoteNode(n, od)
                node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
                node.sdo.MAX_RETRIES = 1
                self.network.add_node(node)
                node.nmt.add_heartbeat_callback(lambda state, n=n: self._on_heartbeat(n, state))
                node.emcy.add_callback(lambda err, n=n: self._on_emcy(n, err))
                self.remote[n] = node
            self._producer_periods(heartbeat_ms if writes else None, heartbeat_ms)
        except Exception:
            self.close()
            raise
        log.info("canopen_link_opened", endpoint=self.endpoint, consumer_s=self.heartbeat_timeout_s)

    def _producer_periods(self, heartbeat_ms: int | None, wanted_ms: int | None = None) -> None:
        """Set (``heartbeat_ms``) or read each node's producer heartbeat time; the consumer time follows from it.
        ``wanted_ms``: what a run would set, named when a node read (not set: a check writes nothing) produces none."""
        longest = 0
        for n in self.nodes:
            period = struct.unpack("<H", self.sdo_read(n, *HEARTBEAT_OBJECT, "producer heartbeat time")[:2])[0]
            if heartbeat_ms is not None and period != heartbeat_ms:
                self.sdo_write(n, *HEARTBEAT_OBJECT, struct.pack("<H", heartbeat_ms), "producer heartbeat time")
                self.heartbeats_found[n], period = period, heartbeat_ms
                log.info("canopen_heartbeat_set", node=n, found_ms=self.heartbeats_found[n], set_ms=heartbeat_ms)
            if period <= 0 and wanted_ms is not None:
                raise SdoFailure(f"node {n} produces no heartbeat now (0x1017 = 0); a run sets it to the station's "
                                 f"heartbeat_ms ({wanted_ms} ms), a check writes nothing", None)
            if period <= 0:
                raise SdoFailure(f"node {n} produces no heartbeat (0x1017 = 0): give the station's heartbeat_ms, "
                                 "without a heartbeat the link's liveness cannot be known", None)
            longest = max(longest, period)
        self.heartbeat_timeout_s = max(self.heartbeat_timeout_s, HEARTBEAT_FACTOR * longest / 1000.0)

    # ------------------------------------------------------------------ heartbeat and EMCY (notifier thread)

    def _on_heartbeat(self, node: int, state: int) -> None:
        with self._cond:
            self._heard[node] = time.monotonic()
            if state == 0:
                self.boots[node] += 1
                log.warning("canopen_node_booted", node=node, boots=self.boots[node])
            self._nmt[node] = state
            self._cond.notify_all()

    def _on_emcy(self, node: int, err: Any) -> None:
        e = Emergency(node, int(err.code), int(err.register), bytes(err.data), time.monotonic())
        with self._cond:
            self.emergencies.append(e)
            del self.emergencies[:-64]
            self._cond.notify_all()
        log.warning("canopen_emcy", node=node, code=f"0x{e.code:04X}", register=f"0x{e.register:02X}")

    def heartbeat_age_s(self) -> float | None:
        """The oldest of the nodes' last heartbeats, in s (None: a node never heard)."""
        now = time.monotonic()
        with self._cond:
            if any(n not in self._heard for n in self.nodes):
                return None
            return max(now - self._heard[n] for n in self.nodes)

    def alive(self) -> bool:
        age = self.heartbeat_age_s()
        return age is not None and age <= self.heartbeat_timeout_s

    def silent_nodes(self) -> list[int]:
        now = time.monotonic()
        with self._cond:
            return [n for n in self.nodes if now - self._heard.get(n, -1e9) > self.heartbeat_timeout_s]

    def nmt_state(self, node: int) -> str:
        return NMT_STATES.get(self._nmt.get(node, -1), "unknown")

    def wait_alive(self, timeout_s: float) -> bool:
        """Wait (bounded) until every node's heartbeat is fresh; whether it is."""
        deadline = time.monotonic() + timeout_s
        while not self.alive():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return False
            with self._cond:
                self._cond.wait(min(remaining, 0.02))
        return True

    def emergencies_since(self, since_s: float) -> list[Emergency]:
        with self._cond:
            return [e for e in self.emergencies if e.at_s >= since_s]

    # ------------------------------------------------------------------ SDO

    def sdo_read(self, node: int, index: int, subindex: int, what: str) -> bytes:
        with self._locks[node]:
            try:
                return bytes(self.remote[node].sdo.upload(index, subindex))
            except canopen.SdoAbortedError as err:
                raise SdoFailure(f"reading {what} (0x{index:04X}:{subindex} on node {node}) aborted: "
                                 f"{sdo_abort_text(err.code)}", err.code) from None
            except (canopen.SdoCommunicationError, OSError, ValueError) as err:
                raise SdoFailure(f"reading {what} (0x{index:04X}:{subindex} on node {node}): {err} within "
                                 f"{self.sdo_timeout_s} s", None) from None
            except Exception as err:  # python-can's CanError (a bus that went away)
                raise SdoFailure(f"reading {what} (0x{index:04X}:{subindex} on node {node}): "
                                 f"{type(err).__name__}: {err}", None) from None

    def sdo_write(self, node: int, index: int, subindex: int, data: bytes, what: str) -> None:
        with self._locks[node]:
            try:
                self.remote[node].sdo.download(index, subindex, data)
            except canopen.SdoAbortedError as err:
                raise SdoFailure(f"writing {what} (0x{index:04X}:{subindex} on node {node}) aborted: "
                                 f"{sdo_abort_text(err.code)}", err.code) from None
            except (canopen.SdoCommunicationError, OSError, ValueError) as err:
                raise SdoFailure(f"writing {what} (0x{index:04X}:{subindex} on node {node}): {err} within "
                                 f"{self.sdo_timeout_s} s; it may or may not have been written", None) from None
            except Exception as err:
                raise SdoFailure(f"writing {what} (0x{index:04X}:{subindex} on node {node}): "
                                 f"{type(err).__name__}: {err}; it may or may not have been written", None) from None

    def read(self, slot: Slot) -> int | float:
        """A slot's raw value (SdoFailure naming the slot and the abort's meaning)."""
        ref = slot.ref
        return slot.decode(self.sdo_read(slot.node, ref.index, ref.subindex, str(slot)))

    def write(self, slot: Slot, raw: int | float) -> None:
        ref = slot.ref
        self.sdo_write(slot.node, ref.index, ref.subindex, slot.encode(raw), str(slot))

    def close(self) -> None:
        """Put back the heartbeat times this link changed (best effort: the device is left as found), stop the
        notifier and shut the bus down (idempotent)."""
        if self._closed:
            return
        self._closed = True
        for n, found_ms in self.heartbeats_found.items():
            try:
                self.sdo_write(n, *HEARTBEAT_OBJECT, struct.pack("<H", found_ms), "producer heartbeat time")
            except Exception as err:  # a lost link: the device keeps the run's period until its next reset
                log.warning("canopen_heartbeat_not_put_back", node=n, found_ms=found_ms, error=str(err))
        with contextlib.suppress(Exception):
            self.network.disconnect()
        log.info("canopen_link_closed", endpoint=self.endpoint)

    def __enter__(self) -> CanopenLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
