"""The CMM driver's protocol handling against scripted I++ DME peers on 127.0.0.1 (real TCP, no simulator): what the
specification's transactions, errors and events mean to the driver (6.2.3, 6.2.4, 6.2.5, 8, 6.3.1), written from the
specification's examples; and the transport taken from the URL (pyserial's ``socket://``).

A peer answers each command line by the rules of its test (``Peer.rules``: method name -> the lines to send, ``TAG``
standing for the command's tag), every other command with ``&`` and ``%``; ``Peer.push`` sends a line unasked.
"""

from __future__ import annotations

import re
import socket
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest
from structlog.testing import capture_logs

from drivers.cmm.ippdme import IppDmeCmm, IppDmeConfig
from drivers.cmm.link import normalise_url
from drivers.cmm.transcript import TranscriptMemory
from drivers.cmm.types import (
    CmmConnectionError,
    CmmDriverError,
    CmmEmergencyStop,
    CmmError,
    CmmInErrorState,
    CmmTimeout,
    ProbeMiss,
)

pytestmark = pytest.mark.timeout(30)
FAST = IppDmeConfig(ack_timeout_s=0.3, query_timeout_s=0.3, motion_timeout_s=0.5, abort_timeout_s=0.3,
                    query_retries=1)
Rule = list[str] | Callable[[str], list[str]]


def _getprop(values: dict[str, str]) -> Callable[[str], list[str]]:
    """A GetProp answering every item asked from `values`, in the order asked."""
    def answer(line: str) -> list[str]:
        names = re.findall(r"([A-Za-z.]+)\(\)", line[6:].removeprefix("GetProp("))
        return ["TAG &", "TAG # " + ", ".join(f"{n}({values[n]})" for n in names), "TAG %"]
    return answer


PROPS = {"Tool.Name": '"Probe1"', "Tool.AvrRadius": "1.5", **{
    f"Tool.PtMeasPar.{p}{part}": v for p in ("Approach", "Search", "Retract")
    for part, v in ((".Min", "0.5"), (".Max", "50"), ("", "10"))}}
SESSION: dict[str, Rule] = {
    "GetDMEVersion": ["TAG &", 'TAG # DMEVersion("1.4.3")', "TAG %"],
    "GetMachineClass": ["TAG &", "TAG # GetMachineClass(CartCMM)", "TAG %"],
    "EnumTools": ["TAG &", 'TAG # "RefTool"', 'TAG # "NoTool"', 'TAG # "Probe1"', "TAG %"],
    "GetProp": _getprop(PROPS),
    "IsHomed": ["TAG &", "TAG # IsHomed(1)", "TAG %"],
    "Get": ["TAG &", "TAG # X(1), Y(2), Z(3)", "TAG %"],
    "GetErrStatusE": ["TAG &", "TAG # ErrStatus(0)", "TAG %"],
}
"""A conforming CMM's answers to the driver's session set-up."""


class Peer:
    """A scripted I++ DME server on 127.0.0.1 (see the module docstring)."""

    def __init__(self, rules: dict[str, Rule]) -> None:
        self.rules = {**SESSION, **rules}
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self.sock.getsockname()[1]}"
        self.received: list[str] = []
        self.conn: socket.socket | None = None
        self._lock = threading.Lock()
        threading.Thread(target=self._serve, daemon=True).start()

    def push(self, line: str) -> None:
        with self._lock:
            assert self.conn is not None
            self.conn.sendall(line.encode("ascii") + b"\r\n")

    def commands(self, method: str) -> list[str]:
        return [c for c in self.received if c[6:].startswith(method + "(")]

    def _serve(self) -> None:
        self.conn, _ = self.sock.accept()
        self.conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        buf = b""
        while data := self.conn.recv(65536):
            buf += data
            while b"\r\n" in buf:
                raw, buf = buf.split(b"\r\n", 1)
                line = raw.decode("ascii")
                self.received.append(line)
                rule = self.rules.get(line[6:].split("(", 1)[0], ["TAG &", "TAG %"])
                lines = rule(line) if callable(rule) else rule
                for out in lines:
                    if out.startswith("SLEEP "):
                        time.sleep(float(out[6:]))
                        continue
                    self.push(out.replace("TAG", line[:5]))

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def peer_factory() -> Iterator[Callable[..., tuple[Peer, IppDmeCmm, TranscriptMemory]]]:
    made: list[tuple[Peer, IppDmeCmm]] = []

    def make(rules: dict[str, Rule] | None = None, **driver: object) -> tuple[Peer, IppDmeCmm, TranscriptMemory]:
        peer = Peer(rules or {})
        transcript = TranscriptMemory()
        cmm = IppDmeCmm(peer.url, driver.pop("config", FAST), transcript=transcript, **driver)  # type: ignore[arg-type]
        made.append((peer, cmm))
        return peer, cmm, transcript

    yield make
    for peer, cmm in made:
        cmm.close()
        peer.close()


# ---------------------------------------------------------------------- transactions and errors (6.2.3, 8)


def test_the_percent_after_an_error_ends_the_transaction_even_when_it_comes_late(peer_factory) -> None:
    """6.2.3.1: '! Error(...)' then '%'; the '%' closes the transaction, here 0.2 s after the error."""
    limit = ["TAG &", 'TAG ! Error(3, 2500, "GoTo", "Machine limit encountered [Move Out Of Limits]")', "SLEEP 0.2",
             "TAG %"]
    peer, cmm, _ = peer_factory({"GoTo": lambda line: limit if "100000" in line else ["TAG &", "TAG %"]})
    cmm.start_session()
    cmm.home()
    with pytest.raises(CmmError) as err:
        cmm.goto(np.array([1e5, 0.0, 0.0]))
    assert err.value.code == 2500 and err.value.severity == 3
    assert not cmm.link.pending
    with pytest.raises(CmmInErrorState):  # 6.2.5: nothing but the error commands until ClearAllErrors
        cmm.goto(np.zeros(3))
    cmm.clear_errors()
    assert peer.received[-2:][0][6:] == "ClearAllErrors()" and peer.received[-1][6:] == "GetErrStatusE()"
    cmm.goto(np.zeros(3))
    assert len(peer.commands("GoTo")) == 2


def test_several_errors_in_one_transaction_are_all_kept(peer_factory) -> None:
    """8: 'Each transaction can generate multiple error messages'; 6.3.1.7's example sends 0511 and 0514."""
    _peer, cmm, _ = peer_factory({"Get": ["TAG &", 'TAG ! Error(2, 0511, "Get", "Error processing method")',
                                         'TAG ! Error(2, 0514, "Get", "Use ClearAllErrors to continue")', "TAG %"]})
    cmm.start_session()
    with pytest.raises(CmmError) as err:
        cmm.where()
    assert err.value.code == 511 and [e.code for e in err.value.errors] == [511, 514]


def test_warnings_are_returned_and_logged_not_raised(peer_factory) -> None:
    """0504 is a warning (severity 1, 6.3.7): the clamped value is read back and planned with."""
    props = {**PROPS, "Tool.PtMeasPar.Approach": "50", "Tool.PtMeasPar.Search": "50", "Tool.PtMeasPar.Retract": "50"}
    peer, cmm, _ = peer_factory({"SetProp": ["TAG &", 'TAG ! Error(1, 0504, "SetProp", "Argument out of range")',
                                             "TAG %"]})
    cmm.start_session()
    cmm.home()
    peer.rules["GetProp"] = _getprop(props)
    cmm.limits.clear()  # as if the server did not state them: the request goes out and is clamped
    with capture_logs() as logs:
        got = cmm.set_touch(80.0, 80.0)
    assert (got.approach_mm, got.search_mm, got.retract_mm) == (50.0, 50.0, 50.0)
    assert [e["code"] for e in logs if e["event"] == "cmm.warning"] == [504]
    assert cmm.link.error_state is None


def test_an_adapted_severity_and_a_foreign_text_are_accepted_and_noted(peer_factory) -> None:
    """8.1 lets a server adapt the severity; a text not the table's is nonconformant but the error is the number's."""
    peer, cmm, _ = peer_factory({"PtMeas": ["TAG &", 'TAG ! Error(3, 1006, PtMeas, "Kein Antasten")', "TAG %"]})
    cmm.start_session()
    cmm.home()
    with capture_logs() as logs, pytest.raises(ProbeMiss):
        cmm.probe(np.array([0.0, 0.0, 10.0]), np.array([0.0, 0.0, 1.0]))
    notes = [e["note"] for e in logs if e["event"] == "cmm.nonconformant"]
    assert any("text is 'Kein Antasten'" in n for n in notes)
    assert any("severity 3, the table's default 2" in n for n in notes)
    assert any("F3 PtMeas is a bare name" in n for n in notes)
    assert cmm.position_mm is not None and peer.received[-1][6:] == "Get(X(), Y(), Z())"  # 1006: asked where


def test_get_error_info_answers_a_string(peer_factory) -> None:
    _peer, cmm, _ = peer_factory({"GetErrorInfo": ["TAG &", 'TAG # "Surface not found"', "TAG %"]})
    cmm.start_session()
    assert cmm.error_info(1006) == "Surface not found"


def test_a_malformed_answer_to_a_query_is_asked_again_under_a_new_tag(peer_factory) -> None:
    answers = iter([["TAG &", "TAG # X(1), Y(2)Z(3)", "TAG %"], ["TAG &", "TAG # X(1), Y(2), Z(3)", "TAG %"]])
    peer, cmm, _ = peer_factory({"Get": lambda line: next(answers)})
    cmm.start_session()
    with capture_logs() as logs:
        np.testing.assert_array_equal(cmm.where(), [1.0, 2.0, 3.0])
    gets = peer.commands("Get")
    assert len(gets) == 2 and gets[0][:5] != gets[1][:5]
    assert [e["raw"] for e in logs if e["event"] == "cmm.malformed_line"] == [f"{gets[0][:5]} # X(1), Y(2)Z(3)"]


# ---------------------------------------------------------------------- events (6.2.4, 9.5)


def test_an_emergency_stop_between_transactions_stops_the_next_motion_unsent(peer_factory) -> None:
    peer, cmm, transcript = peer_factory()
    cmm.start_session()
    cmm.home()
    peer.push('E0000 ! Error(3, 0500, "HealthCheck", "Emergency stop")')
    time.sleep(0.1)
    with pytest.raises(CmmInErrorState) as err:
        cmm.goto(np.zeros(3))
    assert isinstance(err.value.cause, CmmEmergencyStop)
    assert not peer.commands("GoTo") and "E0000 ! Error(3, 0500" in transcript.received()[-1]
    (event,) = cmm.link.events
    assert event.kind == "error" and isinstance(event.error, CmmEmergencyStop) and event.error.tag == "E0000"


def test_an_emergency_stop_during_a_motion_raises_after_its_percent(peer_factory) -> None:
    """The server aborts the pending GoTo (6.2.5: 0006) after the unsolicited 0500; the driver raises the stop."""
    stop = 'E0000 ! Error(3, 0500, "HealthCheck", "Emergency stop")'
    _peer, cmm, _ = peer_factory({"GoTo": ["TAG &", "SLEEP 0.1", stop, 'TAG ! Error(2, 0006, "GoTo", "Transaction '
                                           'aborted (Use ClearAllErrors To Continue)")', "TAG %"]})
    cmm.start_session()
    cmm.home()
    with pytest.raises(CmmEmergencyStop) as err:
        cmm.goto(np.zeros(3))
    assert err.value.tag == "E0000" and 6 in [e.code for e in err.value.errors]
    assert cmm.position_mm is None


def test_an_emergency_stop_during_a_motion_the_server_never_completes_is_what_the_recovery_raises(
        peer_factory) -> None:
    """No '%' after the stop: the driver's AbortE recovery runs (AbortE, ClearAllErrors, status, position) and raises
    the emergency stop, not a timeout; nothing moves until clear_errors()."""
    stop = 'E0000 ! Error(3, 0500, "HealthCheck", "Emergency stop")'
    moves = iter([["TAG &", stop], ["TAG &", "TAG %"]])
    peer, cmm, _ = peer_factory({"GoTo": lambda line: next(moves)})
    cmm.start_session()
    cmm.home()
    with pytest.raises(CmmEmergencyStop):
        cmm.goto(np.zeros(3))
    assert [c[6:] for c in peer.received[-5:]] == ["AbortE()", "ClearAllErrors()", "GetErrStatusE()",
                                                   "GetXtdErrStatus()", "Get(X(), Y(), Z())"]
    with pytest.raises(CmmInErrorState):
        cmm.goto(np.zeros(3))
    assert len(peer.commands("GoTo")) == 1
    cmm.clear_errors()  # released at the machine, then cleared
    cmm.goto(np.zeros(3))
    assert len(peer.commands("GoTo")) == 2


def test_a_tool_changed_by_the_server_is_read_again(peer_factory) -> None:
    from drivers.cmm.types import CmmToolChanged

    peer, cmm, _ = peer_factory()
    cmm.start_session()
    cmm.home()
    peer.push('E0000 # ChangeTool("Probe1")')
    time.sleep(0.1)
    with pytest.raises(CmmToolChanged):
        cmm.goto(np.zeros(3))
    assert [e.kind for e in cmm.link.events] == ["ChangeTool"] and cmm.link.events[0].error is None
    assert cmm.stylus_radius_mm is None
    assert cmm.stylus() == 1.5 and peer.received[-1][6:].startswith("GetProp(Tool.PtMeasPar.Approach()")


# ---------------------------------------------------------------------- sessions and identity (6.3.1, 6.3.2)


def test_a_second_start_session_ends_the_open_one_first(peer_factory) -> None:
    started = iter([["TAG &", "TAG %"], ["TAG &", 'TAG ! Error(3, 0008, "StartSession", "Protocol error")', "TAG %"],
                    ["TAG &", "TAG %"]])
    peer, cmm, _ = peer_factory({"StartSession": lambda line: next(started)})
    cmm.start_session()
    cmm.start_session()
    assert [c[6:] for c in peer.received if "Session" in c or "ClearAll" in c] == [
        "StartSession()", "StartSession()", "ClearAllErrors()", "EndSession()", "StartSession()"]


def test_a_server_before_1_4_and_without_effective_radius_is_served(peer_factory) -> None:
    """GetDMEVersion 0501 (6.3.1.14: before 1.4), OnPtMeasReport(..., ER()) refused: the driver clears and goes on
    with IJK(); the stylus radius from the configuration where Tool.AvrRadius() is unknown."""
    def on_report(line: str) -> list[str]:
        if "ER()" in line:
            return ["TAG &", 'TAG ! Error(3, 0510, "OnPtMeasReport", "Bad property")', "TAG %"]
        return ["TAG &", "TAG %"]

    def getprop(line: str) -> list[str]:
        if "AvrRadius" in line:
            return ["TAG &", 'TAG ! Error(3, 0510, "GetProp", "Bad property")', "TAG %"]
        return _getprop(PROPS)(line)

    config = FAST.model_copy(update={"stylus_radius_mm": 2.0})
    _peer, cmm, _ = peer_factory({"GetDMEVersion": ["TAG &", 'TAG ! Error(3, 0501, "x", "Unsupported command")',
                                                   "TAG %"], "OnPtMeasReport": on_report, "GetProp": getprop},
                                config=config)
    cmm.start_session()
    cmm.home()
    assert cmm.version is None and cmm.stylus_radius_mm == 2.0 and cmm.report_items == ["X", "Y", "Z", "IJK"]


def test_home_only_when_not_homed_and_the_station_tool_activated(peer_factory) -> None:
    tools = iter(['"Probe1"', '"Probe2"'])
    props = dict(PROPS)

    def getprop(line: str) -> list[str]:
        if line.endswith("GetProp(Tool.Name())"):
            props["Tool.Name"] = next(tools)
        return _getprop(props)(line)

    peer, cmm, _ = peer_factory({"EnumTools": ["TAG &", 'TAG # "Probe1"', 'TAG # "Probe2"', "TAG %"],
                                 "GetProp": getprop}, tool="Probe2")
    cmm.start_session()
    cmm.home()
    assert not peer.commands("Home") and len(peer.commands("ChangeTool")) == 1
    assert peer.commands("ChangeTool")[0].endswith('ChangeTool("Probe2")') and cmm.active_tool == "Probe2"
    with pytest.raises(CmmDriverError, match="no tool 'Probe9': EnumTools lists Probe1, Probe2"):
        cmm._change_tool("Probe9")


# ---------------------------------------------------------------------- transport from the URL (6.1)


def test_a_socket_url_without_a_port_gets_the_ipp_port() -> None:
    assert normalise_url("socket://cmm.lab") == "socket://cmm.lab:1294"
    assert normalise_url("socket://10.0.0.5:4000") == "socket://10.0.0.5:4000"
    assert normalise_url("/dev/ttyUSB0") == "/dev/ttyUSB0"


def test_a_peer_that_closes_the_connection_is_a_connection_error(peer_factory) -> None:
    peer, cmm, _ = peer_factory({"IsHomed": ["TAG &"]})
    cmm.start_session()
    threading.Timer(0.1, lambda: peer.conn.shutdown(socket.SHUT_RDWR)).start()
    with pytest.raises((CmmConnectionError, CmmTimeout)):
        cmm.home()


def test_nothing_listening_is_a_connection_error() -> None:
    with socket.create_server(("127.0.0.1", 0)) as s:
        port = s.getsockname()[1]
    with pytest.raises(CmmConnectionError, match="cannot open"):
        IppDmeCmm(f"socket://127.0.0.1:{port}", FAST)


def test_a_wrong_tag_under_a_pending_transaction_is_not_taken_for_its_answer(peer_factory) -> None:
    peer, cmm, _ = peer_factory({"IsHomed": ["00999 &", "00999 # IsHomed(1)", "00999 %"]})
    cmm.start_session()
    with capture_logs() as logs, pytest.raises(CmmTimeout):
        cmm.home()
    assert len(peer.commands("IsHomed")) == 2  # a query: asked once more, then given up
    assert len([e for e in logs if e["event"] == "cmm.unexpected_response"]) == 6
