"""Fuzzing the CMM driver's side of I++ DME: its response parser and checks, its command check, and the live driver
on random replies over a real pty.

Random input must give a clean typed error (or a valid parse), never another exception or a hang. (The simulated
CMM's own reader is fuzzed with the simulator, ``tests/sim_devices``.)
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

from drivers.cmm.forms import check_response
from drivers.cmm.ippdme import IppDmeCmm, IppDmeConfig
from drivers.cmm.types import CmmDriverError, TouchSettings
from drivers.cmm.wire import Item, LineSyntaxError, ResponseLine, check_command, command_line, parse_response
from hilcal.protocols.ippdme import Marker

pytestmark = pytest.mark.timeout(60)

FUZZ = settings(
    deadline=None, max_examples=200, database=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)

tags = st.integers(0, 99999).map(lambda n: f"{n:05d}")
protocol_alphabet = st.sampled_from([*'0123456789 &%#!(),."-+eE XYZIJKError', "\r", "\n", "\x00", "\xff"])
protocolish_text = st.lists(protocol_alphabet, max_size=80).map("".join)
texts = st.one_of(
    st.text(max_size=120),
    st.tuples(tags, protocolish_text).map(lambda t: f"{t[0]} {t[1]}"),
    st.tuples(tags, st.sampled_from("&%#!"), protocolish_text).map(lambda t: f"{t[0]} {t[1]} {t[2]}"),
)


@FUZZ
@given(texts)
def test_the_response_parser_and_checks_never_crash(text: str) -> None:
    try:
        line = parse_response(text)
    except LineSyntaxError:
        return
    assert isinstance(line, ResponseLine) and line.raw == text and text.startswith(line.tag)
    assert line.marker in Marker
    check_response(line)


@FUZZ
@given(texts)
def test_the_command_check_never_crashes(text: str) -> None:
    try:
        check_command(text)
    except LineSyntaxError:
        pass


finite = st.floats(-1e5, 1e5, allow_nan=False)


@FUZZ
@given(tags.filter(lambda t: t != "00000"), finite, finite, finite)
def test_the_driver_reads_what_a_cmm_sends_and_writes_what_the_check_accepts(tag: str, x: float, y: float,
                                                                             z: float) -> None:
    line = parse_response(f"{tag} # X({x:.6f}), Y({y:.6f}),Z({z:.6f}), IJK(0, 0, 1), ER(1.5)")
    got = {it.name: it.args[0] for it in line.values}
    assert got == pytest.approx({"X": x, "Y": y, "Z": z, "IJK": 0.0, "ER": 1.5}, abs=1e-6)
    assert not check_response(line)
    sent = command_line(tag, "PtMeas", Item("X", (x,)), Item("Y", (y,)), Item("Z", (z,)), Item("IJK", (0.0, 0.6, -0.8)))
    check_command(sent)
    assert parse_response(f"{tag} # {sent[6:]}").values[0].args[0].args[0] == pytest.approx(x, abs=1e-6)


class RandomPeer:
    """A real pty whose far end answers every command line with the next fuzzed reply (TAG: the command's tag)."""

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
    st.sampled_from([b"TAG &\r\n", b"TAG %\r\n", b"TAG # X(1), Y(2), Z(3)\r\n", b'TAG ! Error(2, 1006, "m", "t")\r\n',
                     b'E0000 ! Error(3, 0500, "m", "Emergency stop")\r\n', b"E0000 # KeyPress(\"F1\")\r\n"]),
    st.sampled_from([b"00099 %\r\n", b"\r\n", b"TAG # X(1\r\n", b"TAG # X(1), Y(2), Z(3), IJK(0,0,1), ER(1)\r\n"]),
)


@settings(deadline=None, max_examples=60, database=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(reply_parts, max_size=6).map(b"".join))
def test_the_live_driver_on_random_replies(peer: RandomPeer, reply: bytes) -> None:
    """Whatever comes back, a touch returns a point or raises a typed driver error, within its bounded waits."""
    peer.reply = reply
    config = IppDmeConfig(ack_timeout_s=0.03, query_timeout_s=0.03, motion_timeout_s=0.03, abort_timeout_s=0.03,
                          query_retries=1)
    start = time.monotonic()
    with IppDmeCmm(peer.path, config) as cmm:
        cmm.stylus_radius_mm, cmm.touch = 1.5, TouchSettings(5.0, 5.0, 5.0)  # as after a session's set-up
        cmm.report_items = ["X", "Y", "Z"]
        try:
            touch = cmm.probe(np.zeros(3), np.array([0.0, 0.0, 1.0]))
        except CmmDriverError:
            pass
        else:
            assert touch.reported_mm.shape == (3,) and np.all(np.isfinite(touch.reported_mm))
    assert time.monotonic() - start < 2.0
