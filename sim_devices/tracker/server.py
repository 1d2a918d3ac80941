"""The simulated laser tracker on TCP: an emScon server on 127.0.0.1 speaking the packets of
``hilcal.protocols.emscon``, one thread and one ``TrackerSession`` per connection, all sharing one
``TrackerMachine`` (``sim_devices.tracker.machine``).

A session reads whole packets (a header that cannot be a packet's closes the connection: the client is out of step),
decodes each as a command and answers it: every step of the machine's answer after its machine time times
``time_scale``. A packet it cannot read is answered with an ``ErrorResponseT`` (``NotImplemented`` for a command
code the AT4xx definitions lack, ``InvalidInputData`` for anything else). Faults (``sim_devices.tracker.faults``)
are drawn per command: silence (nothing), a late answer, unknown packets before the answer, the answer cut, a beam
break during a measurement. Never imports ``drivers``.
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import threading
from collections.abc import Callable, Mapping
from types import TracebackType
from typing import Any

import numpy as np
import structlog

from hilcal.protocols.emscon import (
    Command,
    DataType,
    FramingError,
    PacketError,
    ResultStatus,
    UnknownPacket,
    decode,
    encode,
    name_of,
    new_answer,
    new_error,
    packet_type,
    take_packets,
)
from sim_devices.tracker.config import TrackerServerConfig
from sim_devices.tracker.faults import FaultInjector, cut
from sim_devices.tracker.machine import Refused, Step, TrackerMachine

log = structlog.get_logger(__name__)

HOST = "127.0.0.1"
WRITE_GIVE_UP_S = 5.0
"""Output nobody reads for this long ends the connection."""
JOIN_TIMEOUT_S = 5.0


class _LinkGone(Exception):
    pass


class TrackerSession:
    """One connection's command handling, transport-free: answers through ``send``, waits through ``wait``."""

    def __init__(self, machine: TrackerMachine, faults: FaultInjector, send: Callable[[bytes], None],
                 wait: Callable[[float], bool]) -> None:
        self.machine = machine
        self.faults = faults
        self.send = send
        self.wait = wait  # sleeps for a duration; True if the server is stopping

    def handle_packet(self, raw: bytes) -> None:
        """Answer one whole packet."""
        try:
            packet = decode(raw, answer=False)
        except UnknownPacket as err:
            command = err.command if err.command is not None else Command.Unknown
            status = ResultStatus.NotImplemented if err.command is not None else ResultStatus.InvalidInputData
            log.info("tracker_sim.unknown_packet", reason=str(err))
            self.send(encode(new_error(command, status)))
            return
        except PacketError as err:
            log.info("tracker_sim.bad_packet", reason=str(err))
            self.send(encode(new_error(Command.Unknown, ResultStatus.InvalidInputData)))
            return
        if packet_type(packet) != DataType.Command:
            log.info("tracker_sim.not_a_command", data_type=name_of(DataType, packet_type(packet)))
            self.send(encode(new_error(Command.Unknown, ResultStatus.InvalidInputData)))
            return
        command = int(packet.packetInfo.command)
        name = Command(command).name
        plan = self.faults.draw(name)
        if plan.silence:
            log.info("tracker_sim.fault_silence", command=name)
            return
        try:
            steps = self.machine.handle(command, packet, plan)
        except Refused as refused:
            log.info("tracker_sim.refused", command=name, status=name_of(ResultStatus, refused.status),
                     detail=refused.detail)
            steps = [Step(refused.duration_s, [new_answer(command, refused.status)])]
        if plan.delay:
            log.info("tracker_sim.fault_delay", command=name, delay_s=self.machine.config.delay_s)
            if self.wait(self.machine.config.delay_s):
                return
        for k, step in enumerate(steps):
            with self.machine.lock:
                self.machine.machine_time_s += step.duration_s
            delay_s = step.duration_s * self.machine.config.time_scale
            if delay_s > 0 and self.wait(delay_s):
                return
            data = b"".join(encode(p) for p in step.packets)
            if k == len(steps) - 1:
                if plan.garbage:
                    log.info("tracker_sim.fault_garbage", command=name)
                    data = b"".join(self.faults.garbage_packet()
                                    for _ in range(self.machine.config.garbage_packets)) + data
                if plan.partial:
                    log.info("tracker_sim.fault_partial", command=name, sent=len(cut(data)), of=len(data))
                    self.send(cut(data))
                    return
            self.send(data)


class TrackerServerHandle:
    """A running simulated tracker: ``address`` (``host:port``), ``port``, ``faults``, ``machine_time_s``."""

    def __init__(self, config: TrackerServerConfig, reflectors: Callable[[], np.ndarray],
                 platform_reflectors: int = 0) -> None:
        if config.move_every_poses and not platform_reflectors:
            raise ValueError("[tracker] move_every_poses counts the poses by the platform's reflectors: give "
                             "platform_reflectors (how many of the reflectors sit on the platform)")
        self.config = config
        self.faults = FaultInjector(config.faults, config.seed, config.hang_after_commands)
        self.machine = TrackerMachine(config, reflectors, platform_reflectors)
        self.host = HOST
        self.commands_handled = 0
        self._stop = threading.Event()
        self._wake_r, self._wake_w = os.pipe()
        self._conns: list[socket.socket] = []
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._listener = socket.create_server((HOST, config.port))
        self._listener.setblocking(False)
        self.port: int = self._listener.getsockname()[1]
        accept = threading.Thread(target=self._accept_loop, name="tracker-sim-accept", daemon=True)
        self._threads.append(accept)
        accept.start()
        log.info("tracker_sim.started", address=self.address, station=config.station.as_array().tolist())

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    @property
    def machine_time_s(self) -> float:
        """The tracker's machine time so far (s, before ``time_scale``): turning, searching, measuring."""
        return self.machine.machine_time_s

    @property
    def station(self) -> np.ndarray:
        """Where the tracker stands now (it moves with ``move_every_poses``): [x, y, z mm, roll, pitch, yaw deg]."""
        with self.machine.lock:
            return self.machine.station_pose()

    def set_station(self, station_pose: np.ndarray) -> None:
        """Set the tracker up at another station [x, y, z mm, roll, pitch, yaw deg] (an operator carrying it)."""
        with self.machine.lock:
            self.machine.place(station_pose)

    @property
    def moves(self) -> int:
        """How often the tracker was set up again so far."""
        return self.machine.moves

    @property
    def measurements(self) -> int:
        """Measurements that gave a result so far."""
        return self.machine.measurements

    def set_obstacles(self, obstacles_base: list[tuple[np.ndarray, float]]) -> None:
        """Replace the obstacles to the line of sight: (centre in the base frame mm, radius mm)."""
        self.machine.set_obstacles(obstacles_base)

    def disconnect_clients(self) -> None:
        """Close every client connection now (a cable pulled)."""
        with self._lock:
            conns = list(self._conns)
        for conn in conns:
            with contextlib.suppress(OSError):
                conn.shutdown(socket.SHUT_RDWR)

    def _accept_loop(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._listener, self._wake_r], [], [])
            if self._wake_r in ready or self._stop.is_set():
                return
            try:
                conn, peer = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            log.info("tracker_sim.connected", peer=f"{peer[0]}:{peer[1]}")
            t = threading.Thread(target=self._serve, args=(conn, f"{peer[0]}:{peer[1]}"),
                                 name=f"tracker-sim {peer[1]}", daemon=True)
            with self._lock:
                self._conns.append(conn)
                self._threads.append(t)
            t.start()

    def _serve(self, conn: socket.socket, peer: str) -> None:
        """Read packets from one connection and answer them until stopped or the peer goes away."""

        def send(data: bytes) -> None:
            try:
                conn.settimeout(WRITE_GIVE_UP_S)
                conn.sendall(data)
            except OSError as err:
                raise _LinkGone(str(err)) from None

        session = TrackerSession(self.machine, self.faults, send, self._stop.wait)
        buf = bytearray()
        try:
            while not self._stop.is_set():
                ready, _, _ = select.select([conn, self._wake_r], [], [])
                if self._wake_r in ready:
                    return
                try:
                    conn.settimeout(0.0)
                    chunk = conn.recv(65536)
                except (BlockingIOError, InterruptedError):
                    continue
                except OSError as err:
                    log.info("tracker_sim.link_closed", peer=peer, error=str(err))
                    return
                if not chunk:
                    log.info("tracker_sim.link_closed", peer=peer)
                    return
                buf += chunk
                try:
                    packets = take_packets(buf)
                except FramingError as err:
                    log.warning("tracker_sim.out_of_step", peer=peer, reason=str(err))
                    return
                for raw in packets:
                    self.commands_handled += 1
                    session.handle_packet(raw)
        except _LinkGone as err:
            log.info("tracker_sim.link_closed", peer=peer, error=str(err))
        except Exception:
            log.exception("tracker_sim.link_failed", peer=peer)
        finally:
            with self._lock:
                if conn in self._conns:
                    self._conns.remove(conn)
            with contextlib.suppress(OSError):
                conn.close()

    def close(self) -> None:
        """Stop every thread and close every socket; idempotent."""
        if self._stop.is_set():
            return
        self._stop.set()
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")
        self.disconnect_clients()
        with self._lock:
            threads = list(self._threads)
        for t in threads:
            t.join(JOIN_TIMEOUT_S)
            if t.is_alive():
                log.warning("tracker_sim.thread_did_not_stop", thread=t.name)
        self._listener.close()
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)
        log.info("tracker_sim.stopped", address=self.address, machine_time_s=round(self.machine.machine_time_s, 3),
                 measurements=self.machine.measurements, moves=self.machine.moves)

    def __enter__(self) -> TrackerServerHandle:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


def start_tracker_server(reflectors: Callable[[], np.ndarray],
                         config: TrackerServerConfig | Mapping[str, Any] | None = None,
                         platform_reflectors: int = 0) -> TrackerServerHandle:
    """Start the simulated tracker; ``reflectors()`` gives the reflectors' true centres now, (N, 3) mm in the base
    frame (``sim_devices.tracker.targets.rig_reflectors`` for the rig's spheres), the first ``platform_reflectors`` of
    them on the platform (needed by ``move_every_poses``). A context manager."""
    if config is None:
        cfg = TrackerServerConfig()
    elif isinstance(config, TrackerServerConfig):
        cfg = config
    else:
        cfg = TrackerServerConfig.model_validate(dict(config))
    return TrackerServerHandle(cfg, reflectors, platform_reflectors)
