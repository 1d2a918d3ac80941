"""The CMM driver's transaction layer replays NIST's ClientServerLogs: a replay server on 127.0.0.1 plays each
``X_Server.log``'s lines to the driver as it sends the commands of ``X_Client.log`` through ``IppLink`` (one test per
log). The server checks every command line against the log; the driver parses every response line as the
specification says, and reads the data it would use (reports, flags, strings, properties) with its own readers
(``drivers.cmm.answers``).

What a log does that 1.4.3 does not (NIST's reference server and client are of the 1.4 era) is said per log in
``ODDITIES``: the notes the driver logs as ``cmm.nonconformant``, the errors it raises, the commands it refuses to
send (6.1.4.2 syntax; 6.3.1.5), the waits it gives up (a motion the client aborts, overlapped transactions).
"""

from __future__ import annotations

import socket
import threading
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest
from structlog.testing import capture_logs

from drivers.cmm import answers
from drivers.cmm.link import CommandRefused, IppLink, LinkConfig, LinkTimeout
from drivers.cmm.transcript import TranscriptMemory
from drivers.cmm.types import CmmError, CmmInErrorState
from tests.conformance.nist_files import LogRecord, nist_dir, read_log
from tests.conformance.nist_grammar import command_problem

pytestmark = [pytest.mark.timeout(60), pytest.mark.skipif(nist_dir() is None, reason="NIST's test files are absent")]

LOGS = sorted(p.name.removesuffix("_Client.log").removesuffix(".Client.log")
              for p in (nist_dir() / "ClientServerLogs").glob("*Client.log")) if nist_dir() else []
WAIT_S = 0.3
"""How long the replay waits for a transaction's '%' (the replay server answers at once; only a transaction whose
completion the log makes wait for a later command times out)."""


class ReplayServer:
    """Plays a server log: after each command line it receives and expects, the lines the log sent next."""

    def __init__(self) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.cond = threading.Condition()
        self.script: list[tuple[str, str]] = []
        self.pos = 0
        self.mismatches: list[tuple[str, tuple[str, str] | None]] = []
        self.sent: list[str] = []
        self.conn: socket.socket | None = None
        threading.Thread(target=self._serve, daemon=True).start()

    def load(self, records: list[LogRecord]) -> None:
        with self.cond:
            self.script = [(r.direction, r.text) for r in records if r.direction != "note"]
            self.pos, self.mismatches, self.sent = 0, [], []
            self._emit()

    def skip_command(self) -> None:
        """The driver refused to send the next command: skip it and what the log answered to it."""
        with self.cond:
            assert self.script[self.pos][0] == "received"
            self.pos += 1
            self._emit(send=False)

    def _emit(self, send: bool = True) -> None:
        while self.pos < len(self.script) and self.script[self.pos][0] == "sent":
            if send and self.conn is not None:
                self.sent.append(self.script[self.pos][1])  # before the line leaves: the driver may see it at once
                self.conn.sendall(self.script[self.pos][1].encode("latin-1") + b"\r\n")
            self.pos += 1

    def _serve(self) -> None:
        self.conn, _ = self.sock.accept()
        self.conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # lines at once, as a CMM server sends them
        buf = b""
        while data := self.conn.recv(65536):
            buf += data
            while b"\r\n" in buf:
                raw, buf = buf.split(b"\r\n", 1)
                with self.cond:
                    expected = self.script[self.pos] if self.pos < len(self.script) else None
                    if expected != ("received", raw.decode("latin-1")):
                        self.mismatches.append((raw.decode("latin-1"), expected))
                        continue
                    self.pos += 1
                    self._emit()


@dataclass
class Replay:
    """What the driver met replaying one log."""

    outcomes: Counter = field(default_factory=Counter)
    errors: list[int] = field(default_factory=list)
    """Error numbers the driver raised (typed CmmError), in order."""
    refused: list[str] = field(default_factory=list)
    in_error: list[str] = field(default_factory=list)
    timed_out: list[str] = field(default_factory=list)
    late_errors: list[int] = field(default_factory=list)
    """Error numbers of the transactions that completed after their wait (an aborted motion's 0006)."""
    daemon_reports: int = 0
    notes: set[tuple[str, str]] = field(default_factory=set)
    read: list[object] = field(default_factory=list)
    """What the driver's readers made of the data (a few per log)."""


@pytest.fixture(scope="module")
def harness() -> Iterator[tuple[ReplayServer, IppLink]]:
    server = ReplayServer()
    link = IppLink(f"socket://127.0.0.1:{server.port}", LinkConfig(ack_timeout_s=WAIT_S, query_timeout_s=WAIT_S,
                                                                   query_retries=0))
    yield server, link
    link.close()


def _read(link: IppLink, tx, report_items: list[str], out: Replay) -> None:
    """Read a completed transaction's data as the driver would."""
    method = tx.method
    if method in ("Get", "GetProp", "GetPropE") and tx.data:
        out.read.append(answers.report(answers.one_line(tx), answers.requested_items(tx.line), link.note))
    elif method == "PtMeas" and tx.data:
        out.read.append(answers.positions(answers.one_line(tx), report_items, link.note))
    elif method in ("IsHomed", "GetErrStatusE", "IsUserEnabled"):
        out.read.append(answers.flag(tx, {"GetErrStatusE": "ErrStatus"}.get(method, method)))
    elif method in ("EnumTools", "GetErrorInfo"):
        out.read.append(answers.strings(tx))
    elif method == "GetDMEVersion":
        out.read.append(answers.string_item(tx, "DMEVersion"))
    elif method == "GetMachineClass":
        out.read.append(answers.machine_class(tx, link.note))


def replay(name: str, server: ReplayServer, link: IppLink) -> Replay:
    """Send the client log's commands, wait for each transaction, read its data; the server log answers."""
    folder = nist_dir() / "ClientServerLogs"
    sep = "_" if (folder / f"{name}_Client.log").exists() else "."
    client, server_log = read_log(folder / f"{name}{sep}Client.log"), read_log(folder / f"{name}{sep}Server.log")
    server.load(server_log)
    link.transcript = transcript = TranscriptMemory()
    out = Replay()
    report_items = ["X", "Y", "Z"]
    late = []
    reports_before = len(link.reports)
    with capture_logs() as logs:
        for rec in (r for r in client if r.direction == "sent"):
            tag, text = rec.text[:5], rec.text[6:]
            try:
                tx = link.send_text(text, tag)
            except CommandRefused:
                out.refused.append(rec.text)
                server.skip_command()
                continue
            except CmmInErrorState:
                out.in_error.append(rec.text)
                server.skip_command()
                continue
            try:
                link.wait(tx, WAIT_S)
            except LinkTimeout:
                out.timed_out.append(rec.text)
                late.append(tx)
                continue
            try:
                link.outcome(tx)
            except CmmError as err:
                out.errors.append(err.code)
                continue
            out.outcomes[tx.method] += 1
            if tx.method == "OnPtMeasReport":
                report_items = answers.requested_items(tx.line)
            elif tx.method == "StartSession":
                report_items = ["X", "Y", "Z"]
            _read(link, tx, report_items, out)
        for tx in late:
            assert tx.done, f"{tx.line} never completed"
            try:
                link.outcome(tx)
            except CmmError as err:
                out.late_errors.append(err.code)
    out.daemon_reports = len(link.reports) - reports_before
    out.notes = {(e["kind"], e["note"]) for e in logs if e["event"] == "cmm.nonconformant"}
    malformed = [e for e in logs if e["event"] in ("cmm.malformed_line", "cmm.unexpected_response")]
    assert not malformed, malformed
    assert not server.mismatches, server.mismatches
    assert not link.pending, f"transactions left incomplete: {list(link.pending)}"
    sent = [r.text for r in client if r.direction == "sent" and r.text not in (*out.refused, *out.in_error)]
    assert transcript.sent() == sent
    assert transcript.received() == server.sent, "the transcript holds every line as it came"
    if not out.refused and not out.in_error:
        received = [r.text for r in client if r.direction == "received"]
        assert transcript.received() == received, "the driver got what NIST's client got, line for line"
    return out


@dataclass(frozen=True)
class Oddities:
    """What a log does that 1.4.3 does not, and what the driver does about it."""

    why: str = ""
    notes: frozenset[str] = frozenset()
    """Beginnings of the texts of the notes logged (``cmm.nonconformant``)."""
    errors: dict[int, int] = field(default_factory=dict)
    """Error numbers raised as typed CmmError, and how often."""
    timed_out: int = 0
    late_errors: tuple[int, ...] = ()
    daemon_reports: int = 0
    in_error: tuple[str, ...] = ()
    refused: int = 0
    read: tuple[object, ...] = ()
    """The first things the driver's readers made of the data."""


REORDERED = "items reported in another order than asked"
VECTOR = "a parenthesised number list is no data form"
CLASS_STRING = ("GetMachineClass answered with a String", "GetMachineClass(\"CartCMMWithRotaryTable\"): a String")
ODDITIES: dict[str, Oddities] = {
    "AbortE_TestWhileMoving": Oddities(
        "the client aborts a GoTo while it moves: the GoTo's wait times out, AbortE completes it with 0006 (in the "
        "1.4 text) before AbortE's own '%'; OnMoveReportE's daemon reports come after its '%'",
        frozenset({"error 0006's text before 1.4.3"}), timed_out=1, late_errors=(6,), daemon_reports=18),
    "AlignPart": Oddities("AlignPart's data as a parenthesised list", frozenset({VECTOR})),
    "AlignTool": Oddities("AlignTool's data as a parenthesised list", frozenset({VECTOR})),
    "DCXPart": Oddities(
        "GetMachineClass answers a String (1.4); PtMeas reports come in the server's order, not OnPtMeasReport's; "
        "the client overlaps PtMeas 00211 and 00212 (00211's '%' after 00212's '&'), so 00211's wait times out and it "
        "completes during 00212's; a daemon reports all along",
        frozenset({REORDERED, *CLASS_STRING}), timed_out=1, daemon_reports=264,
        read=("CartCMMWithRotaryTable", "1.4", False, ["NoTool", "RefTool", "Probe1"])),
    "EnumTools": Oddities(read=(["NoTool", "RefTool", "Probe1"],)),
    "Error": Oddities("a GoTo out of the machine's volume: 1008, severity 3", errors={1008: 1}),
    "Get": Oddities("the server sorts the items it reports (X, Y, Z, then the tool's axes, R first)",
                    frozenset({REORDERED}), read=({"R": (0.0,)}, {"X": (0.0,)}, {"Y": (0.0,)}, {"Z": (0.0,)})),
    "GetDMEVersion": Oddities(read=("1.4",)),
    "GetErrStatusE": Oddities(read=(False,)),
    "GetErrorInfo": Oddities("GetErrorInfo answers a bare String (6.3.1.6)", read=(["Daemon does not exist"],)),
    "GetMachineClass": Oddities("GetMachineClass answers a String (1.4)", frozenset(CLASS_STRING),
                                read=("CartCMMWithRotaryTable",)),
    "GetProp": Oddities(read=({"Tool.Name": ("Probe1",)}, {"FoundTool.Name": ("RefTool",),
                                                            "FoundTool.Id": ("RefToolId",)})),
    "GetPropE": Oddities(read=({"Tool.Name": ("Probe1",)}, {"FoundTool.Name": ("RefTool",),
                                                             "FoundTool.Id": ("RefToolId",)})),
    "GoTo_Test": Oddities("a daemon reports while GoTo moves", daemon_reports=8),
    "Home_Test": Oddities(read=({"X": (10.0,), "Y": (11.0,), "Z": (12.0,)}, {"X": (0.0,), "Y": (0.0,), "Z": (0.0,)},
                                True)),
    "IsHomed": Oddities(read=(False, True)),
    "PtMeas": Oddities("the server reports IJK first and sorts the rest, whatever OnPtMeasReport asked",
                       frozenset({REORDERED}),
                       read=({"IJK": (0.0, 0.0, 1.0), "X": (3.06205,), "Y": (-24.26795,), "Z": (32.73005,)},)),
    "SetProp": Oddities(read=({"Tool.PtMeasPar.Accel": (54.2,)}, {"Tool.PtMeasPar.Accel.Act": (6.42,)})),
    "StopDaemon": Oddities("StopDaemon of a daemon that does not exist: 0513", errors={513: 1}),
    "allCmdOK": Oddities("1.4 forms throughout", frozenset({VECTOR, REORDERED, *CLASS_STRING})),
    "allResOK": Oddities("StopDaemon of no daemon (0513); 1.4 forms", frozenset({VECTOR, *CLASS_STRING}),
                         errors={513: 1}),
    "checkerCmdErrors": Oddities(
        "commands that NIST's checker refuses, each answered with its error, most in NIST's own words; the client "
        "sends Get(X()) right after AbortE, which 6.3.1.5 forbids (ClearAllErrors first): the driver refuses to",
        frozenset({"error 0502's text is 'Incorrect Arguments'"}),
        errors={507: 43, 1010: 19, 502: 12, 1502: 7, 1503: 3, 1008: 2, 510: 2, 515: 1, 1007: 1, 513: 1},
        in_error=("05403 Get(X())",)),
    "numbersErrorCmd": Oddities("numbers that break 6.1.4.2: the driver refuses to send them", refused=7),
    "parserCmdErrors": Oddities(
        "commands that break the syntax: the driver refuses those NIST's parser refuses for their syntax and sends "
        "the rest, which the server answers with 0502/0509 in its own capitalisation",
        frozenset({"error 0502's text is 'Incorrect Arguments'", "error 0509's text is 'Bad Argument'"}),
        errors={502: 153, 509: 54, 1007: 1, 507: 1}, refused=54),
}


@pytest.mark.parametrize("name", LOGS)
def test_replay(name: str, harness: tuple[ReplayServer, IppLink]) -> None:
    server, link = harness
    out = replay(name, server, link)
    odd = ODDITIES.get(name, Oddities())
    for cmd in out.refused:
        assert command_problem(cmd) is not None, f"the driver refused {cmd!r}, which NIST's parser accepts"
    assert len(out.refused) == odd.refused
    assert tuple(out.in_error) == odd.in_error
    assert dict(Counter(out.errors)) == odd.errors
    assert len(out.timed_out) == odd.timed_out
    assert tuple(out.late_errors) == odd.late_errors
    assert out.daemon_reports == odd.daemon_reports
    assert tuple(out.read[:len(odd.read)]) == odd.read
    got = {text for _, text in out.notes}
    assert {n for n in odd.notes if not any(g.startswith(n) for g in got)} == set(), "a note expected was not made"
    assert {g for g in got if not any(g.startswith(n) for n in odd.notes)} == set(), "an unexpected note"
