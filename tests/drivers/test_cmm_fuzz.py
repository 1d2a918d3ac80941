"""Fuzzing the CMM protocol: both parsers, the simulator's session and both live ends on random input.

Random input must give a clean typed error (or a valid parse), never another exception or a hang.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.cmm.base import CmmDriverError
from drivers.cmm.serial import (
    GarbageLine,
    MalformedResponse,
    Response,
    SerialCmm,
    SerialCmmConfig,
    parse_response_line,
)
from hilcal.protocols.cmm import Marker
from hilcal.robot import default_robot
from sim_devices.cmm.commands import CommandRejected, ParsedCommand, parse_command_line
from sim_devices.cmm.config import CmmServerConfig, FaultRates
from sim_devices.cmm.faults import FaultInjector
from sim_devices.cmm.server import CmmServerHandle, start_cmm_server
from sim_devices.cmm.session import CmmMachine, CmmSession
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(60)

ROBOT = default_robot()
FUZZ = settings(
    deadline=None, max_examples=200, database=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)

tags = st.integers(0, 99999).map(lambda n: f"{n:05d}")
protocol_alphabet = st.sampled_from([*'0123456789 &%#!(),."-+eE XYZIJKError', "\r", "\n", "\x00", "\xff"])
protocolish_text = st.lists(protocol_alphabet, max_size=80).map("".join)
lines = st.one_of(
    st.binary(max_size=200),
    st.text(max_size=120).map(lambda s: s.encode("utf-8", "surrogatepass")),
    st.tuples(tags, protocolish_text).map(lambda t: f"{t[0]} {t[1]}".encode("latin-1")),
)


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    return SimulatedRig(ROBOT, RigConfig(seed=5, errors=load_errors("table3")))


# ---------------------------------------------------------------------- pure parsers


@FUZZ
@given(lines)
def test_driver_response_parser_never_crashes(raw: bytes) -> None:
    try:
        resp = parse_response_line(raw)
    except (GarbageLine, MalformedResponse):
        return
    assert isinstance(resp, Response)
    assert len(resp.tag) == 5 and resp.tag.isdigit()
    assert raw.startswith(resp.tag.encode())


finite = st.floats(-1e5, 1e5, allow_nan=False)


@FUZZ
@given(tags, finite, finite, finite)
def test_driver_reads_what_a_cmm_would_send(tag: str, x: float, y: float, z: float) -> None:
    resp = parse_response_line(f"{tag} # X({x:.6f}), Y({y:.6f}),Z({z:.6f})".encode())
    assert resp.marker is Marker.DATA and resp.tag == tag
    got = {it.name: it.args[0] for it in resp.items}
    assert got == pytest.approx({"X": x, "Y": y, "Z": z}, abs=1e-6)
    err = parse_response_line(f'{tag} ! Error(2, 1006, "PtMeas", "Surface (not) found, {x}")'.encode())
    assert err.marker is Marker.ERROR and err.items[0].args[1] == 1006.0


@FUZZ
@given(lines)
def test_server_command_parser_never_crashes(raw: bytes) -> None:
    try:
        cmd = parse_command_line(raw)
    except CommandRejected as rej:
        assert len(rej.tag) == 5 and rej.tag.isdigit()
        return
    assert isinstance(cmd, ParsedCommand)


@FUZZ
@given(tags, finite, finite, finite)
def test_server_reads_what_a_driver_would_send(tag: str, x: float, y: float, z: float) -> None:
    if tag == "00000":
        return
    cmd = parse_command_line(f"{tag} PtMeas(X({x}), Y({y}),Z({z}), IJK(0, 0.5, -1e0))".encode())
    assert cmd.tag == tag and cmd.call.name == "PtMeas"
    assert [a.name for a in cmd.call.args] == ["X", "Y", "Z", "IJK"]
    assert cmd.call.args[3].args == (0.0, 0.5, -1.0)


@FUZZ
@given(st.lists(lines, min_size=1, max_size=5))
def test_server_session_answers_every_line_with_valid_responses(rig: SimulatedRig, batch: list[bytes]) -> None:
    """The simulator's session on random lines: no exception, and every output line is a valid response."""
    config = CmmServerConfig(time_scale=0.0)
    out: list[bytes] = []
    session = CmmSession(CmmMachine(ROBOT, rig, config), FaultInjector(FaultRates(), 0), out.append, lambda _s: False)
    for raw in [b"00001 StartSession()", b"00002 Home()", *batch]:
        session.handle_line(raw)
    text = b"".join(out)
    assert text.endswith(b"\r\n")
    for line in text.split(b"\r\n")[:-1]:
        assert isinstance(parse_response_line(line), Response)


# ---------------------------------------------------------------------- live ends


@pytest.fixture(scope="module")
def server(rig: SimulatedRig) -> Iterator[CmmServerHandle]:
    handle = start_cmm_server(ROBOT, rig, CmmServerConfig(time_scale=0.0))
    yield handle
    handle.close()


def _read_until(fd: int, marker: bytes, timeout_s: float) -> bytes:
    buf = b""
    deadline = time.monotonic() + timeout_s
    while marker not in buf:
        left = deadline - time.monotonic()
        assert left > 0, f"no {marker!r} within {timeout_s} s; got {buf[-200:]!r}"
        ready, _, _ = select.select([fd], [], [], left)
        if ready:
            buf += os.read(fd, 4096)
    return buf


@settings(
    deadline=None,
    max_examples=200,
    database=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(st.binary(max_size=700))
def test_live_server_survives_random_bytes(server: CmmServerHandle, noise: bytes) -> None:
    """Random bytes, then a line break and a known command: the server still answers it."""
    fd = os.open(server.path, os.O_RDWR | os.O_NOCTTY)
    try:
        tty.setraw(fd)
        os.write(fd, noise + b"\r\n54321 GetErrorInfo(1)\r\n")
        reply = _read_until(fd, b"54321 %\r\n", 2.0)
        assert b'54321 # ErrorInfo(0001, "Illegal tag")' in reply
    finally:
        os.close(fd)


class RandomPeer:
    """A real pty whose far end answers every command line with the next fuzzed reply."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.reply = b""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        buf = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.02)
            if ready:
                buf += os.read(self.master, 4096)
                while b"\n" in buf:
                    line, buf = buf.split(b"\n", 1)
                    os.write(self.master, self.reply.replace(b"TAG", line[:5]))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture(scope="module")
def peer() -> Iterator[RandomPeer]:
    p = RandomPeer()
    yield p
    p.close()


reply_parts = st.one_of(
    st.binary(max_size=40),
    st.sampled_from([b"TAG &\r\n", b"TAG %\r\n", b"TAG # X(1), Y(2), Z(3)\r\n", b'TAG ! Error(2, 1006, "m", "t")\r\n']),
    st.sampled_from([b"00099 %\r\n", b"\r\n", b"TAG # X(1\r\n"]),
)


@settings(
    deadline=None,
    max_examples=60,
    database=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(st.lists(reply_parts, max_size=6).map(b"".join))
def test_live_driver_on_random_replies(peer: RandomPeer, reply: bytes) -> None:
    """Whatever comes back, the driver returns a point or raises a typed driver error, within its time bounds."""
    peer.reply = reply
    config = SerialCmmConfig(ack_timeout_s=0.03, command_timeout_s=0.03, max_retries=1, poll_s=0.005)
    start = time.monotonic()
    with SerialCmm(peer.path, config) as cmm:
        try:
            point = cmm.probe(np.zeros(3), np.array([0.0, 0.0, 1.0]))
        except CmmDriverError:
            pass
        else:
            assert point.shape == (3,) and np.all(np.isfinite(point))
    assert time.monotonic() - start < 2.0
