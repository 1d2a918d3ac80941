"""One link's I++ DME session on the simulated CMM: transactions, the two queues, the error state, daemons, events.

Transactions (6.2.3): each command is acknowledged (``&``) as it is read; commands with a command tag then wait in
the normal queue and are answered in order by the session's worker (``#`` and ``!`` lines, ``%`` always last, also
after ``!``), so the reader keeps reading while a motion takes machine time. Commands with an event tag (AbortE,
GetErrStatusE, GetPropE, OnMoveReportE; 6.2.1) are answered at once by the reader; lines with an event tag may come at
any time (6.2.3). A line whose tag cannot be read is answered ``E0000 ! Error(2, 0001, ...)`` alone (6.2.1).

Errors (6.2.5, 8): an error of severity 2 or more aborts the pending transactions (``0006`` each, then ``%``) and
puts the session in its error state: every method but GetErrStatusE, GetXtdErrStatus, ClearAllErrors (and AbortE,
which must always be able to stop the machine) is then answered 0511 and 0514 as 6.3.1.7's example shows, until
ClearAllErrors. AbortE (6.3.1.5) stops the motion, answers "Transaction aborted" for the executing and the pending
non-event commands, sends its own ``%`` after them, and leaves only ClearAllErrors to the client (else 0511, 0514).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import structlog

from hilcal.protocols.ippdme import (
    SESSIONLESS_METHODS,
    WHILE_IN_ERROR_METHODS,
    Code,
    Marker,
    Method,
)
from sim_devices.cmm import methods
from sim_devices.cmm.faults import FaultInjector, FaultPlan
from sim_devices.cmm.handlers import Handlers, Reply, SessionState, measured_item
from sim_devices.cmm.machine import CmmMachine, MotionStopped
from sim_devices.cmm.methods import ArgumentError
from sim_devices.cmm.responses import SERVER_EVENT_TAG, line
from sim_devices.cmm.wire import Command, LineError, read_command

log = structlog.get_logger(__name__)

MAX_PENDING = 100
"""Transactions waiting in the normal queue beyond this delay the next acknowledgement (6.2.3)."""
ABORT_WAIT_S = 10.0
"""AbortE waits at most this long for the executing motion to stop (real time)."""
MOVING = frozenset({Method.HOME, Method.GO_TO, Method.PT_MEAS, Method.CHANGE_TOOL})
REPORT_INTERVAL_S = 0.1
"""6.3.2.7: at most 10 move reports per second (machine time)."""
TIME_TOL_S = 1e-9
"""Sums of machine-time samples compared with this slack."""


@dataclass
class Job:
    """A transaction of the normal queue: its command (or the error its line earned) and its faults."""

    tag: str
    method: str
    command: Command | None
    error: LineError | None
    plan: FaultPlan
    aborted: bool = False


class CmmSession:
    """One connection's protocol state; reads command lines, answers through ``send``."""

    def __init__(self, machine: CmmMachine, faults: FaultInjector, send: Callable[[bytes], None],
                 stop: threading.Event) -> None:
        self.machine = machine
        self.faults = faults
        self._send = send
        self._stop = stop
        self._closed = threading.Event()
        self._out = threading.Lock()
        self._cv = threading.Condition()
        self._state_lock = threading.RLock()
        """Held while a handler reads or changes the session's state (the reader and the worker both answer)."""
        self._queue: deque[Job] = deque()
        self._current: Job | None = None
        self._abort_asked = False
        self.state = SessionState()
        self.handlers = Handlers(machine, self.state)
        machine.move_listeners.append(self)
        machine.event_listeners.append(self._on_machine_event)
        self._worker = threading.Thread(target=self._work, name="cmm-sim-session", daemon=True)
        self._worker.start()

    # ------------------------------------------------------------------ output

    def _write(self, data: bytes) -> None:
        with self._out:
            self._send(data)

    def _write_event(self, data: bytes) -> None:
        """A line another thread raises (a move report, an unsolicited error): a link that just went away drops it
        instead of failing the motion that raised it."""
        try:
            self._write(data)
        except OSError as err:
            log.info("cmm_sim.event_dropped", error=str(err))

    def _finish(self, tag: str, body: list[bytes], plan: FaultPlan, ack: bool = False) -> None:
        """A transaction's lines after (or, with ``ack``, with) its acknowledgement, with the planned faults."""
        lines = [*body, line(tag, Marker.DONE)]
        if plan.garbage:
            lines[-1:-1] = [self.faults.garbage_line() for _ in range(self.machine.config.garbage_lines)]
        head = line(tag, Marker.ACK) if ack else b""
        if plan.partial:
            log.info("cmm_sim.fault_partial", tag=tag, sent=lines[0][: len(lines[0]) // 2])
            self._write(head + lines[0][: len(lines[0]) // 2])
            return
        self._write(head + b"".join(lines))

    # ------------------------------------------------------------------ reading (the link's thread)

    def handle_line(self, raw: bytes) -> None:
        """Answer one received line (its LF removed)."""
        try:
            cmd = read_command(raw)
        except LineError as err:
            self._refused_line(err, raw)
            return
        plan = self.faults.draw(cmd.method)
        if plan.silence:
            log.info("cmm_sim.fault_silence", tag=cmd.tag, command=cmd.method)
            return
        if cmd.is_event:
            self._event(cmd, plan)
        else:
            self._enqueue(Job(cmd.tag, cmd.method, cmd, None, plan))

    def _refused_line(self, err: LineError, raw: bytes) -> None:
        log.info("cmm_sim.rejected", code=int(err.code), tag=err.tag, detail=err.detail, raw=raw[:200])
        plan = self.faults.draw(err.method)
        if plan.silence:
            return
        if err.tag is None:
            reply = Reply(SERVER_EVENT_TAG, err.method or "ReadTag")
            reply.error(err.code)
            self._serious(reply)
            self._write(reply.lines[0])
        elif err.tag.startswith("E"):
            reply = Reply(err.tag, err.method)
            reply.error(err.code)
            self._serious(reply)
            self._finish(err.tag, reply.lines, plan, ack=True)
        else:
            self._enqueue(Job(err.tag, err.method, None, err, plan))

    def _enqueue(self, job: Job) -> None:
        with self._cv:
            self._cv.wait_for(lambda: len(self._queue) < MAX_PENDING or self._stopping(), timeout=None)
            self._write(line(job.tag, Marker.ACK))
            self._queue.append(job)
            self._cv.notify_all()

    def _stopping(self) -> bool:
        return self._stop.is_set() or self._closed.is_set()

    def _event(self, cmd: Command, plan: FaultPlan) -> None:
        """An event-tag command, answered at once (the fast queue, 4.1)."""
        if cmd.method == Method.ABORT_E and self.state.in_session and not self.state.aborted and not cmd.args:
            self._abort(cmd, plan)
            return
        reply = Reply(cmd.tag, cmd.method)
        self._answer(cmd, reply)
        self._serious(reply)
        self._finish(cmd.tag, reply.lines, plan, ack=True)

    def _abort(self, cmd: Command, plan: FaultPlan) -> None:
        """6.3.1.5: stop the motion; 0006 for the executing and the pending commands; AbortE's ``%`` after them."""
        self._write(line(cmd.tag, Marker.ACK))
        with self._cv:
            for job in self._queue:
                job.aborted = True
            self.state.aborted = True
            with self.machine.stop_lock:
                self._abort_asked = True
            if self._current is not None:
                self.machine.request_stop("abort")
            self._cv.wait_for(lambda: (not self._queue and self._current is None) or self._stopping(),
                              timeout=ABORT_WAIT_S)
            with self.machine.stop_lock:
                self._abort_asked = False
        log.info("cmm_sim.aborted", tag=cmd.tag)
        self._finish(cmd.tag, [], plan)

    # ------------------------------------------------------------------ the error state

    def _serious(self, reply: Reply) -> None:
        """After errors of severity 2 or more: the pending transactions are aborted, the session in its error state."""
        if not reply.aborts_pending:
            return
        with self._cv:
            self.state.errors.extend(e for e in reply.serious if e not in self.state.errors)
            for job in self._queue:
                job.aborted = True

    def _refusal(self, method: str) -> bool:
        """Whether the session's error state (or AbortE) refuses this method. EndSession and StartSession always pass:
        "sending an EndSession() followed by a StartSession will start a new session in any case" (6.3.1)."""
        if method in SESSIONLESS_METHODS:
            return False
        if self.state.aborted:
            return method != Method.CLEAR_ALL_ERRORS
        return bool(self.state.errors) and method not in (*WHILE_IN_ERROR_METHODS, Method.ABORT_E)

    def _answer(self, cmd: Command, reply: Reply) -> None:
        """Answer a method that does not move the machine, its state checks first."""
        self.machine.look()  # the platform may have struck the ball since the last command
        with self._state_lock:
            if not self.state.in_session and cmd.method not in SESSIONLESS_METHODS:
                reply.error(Code.ILLEGAL_COMMAND)
            elif self._refusal(cmd.method):
                reply.refuse()
            elif cmd.method not in methods.SUPPORTED:
                reply.error(Code.UNSUPPORTED_COMMAND)
            else:
                try:
                    self.handlers.call(cmd, reply)
                except ArgumentError as err:
                    log.info("cmm_sim.rejected", tag=cmd.tag, code=int(err.code), detail=err.detail)
                    reply.error(err.code)

    # ------------------------------------------------------------------ the normal queue (the worker's thread)

    def _work(self) -> None:
        while True:
            with self._cv:
                self._cv.wait_for(lambda: self._queue or self._stopping())
                if self._stopping():
                    return
                job = self._current = self._queue.popleft()
            try:
                self._execute(job)
            except Exception:
                if self._stopping():  # the link or the server went away while answering
                    return
                log.exception("cmm_sim.job_failed", tag=job.tag, method=job.method)
                failed = Reply(job.tag, job.method)
                failed.error(Code.ERROR_PROCESSING_METHOD)
                self._finish(job.tag, failed.lines, FaultPlan())
            finally:
                with self._cv:
                    self._current = None
                    self._cv.notify_all()

    def _execute(self, job: Job) -> None:
        reply = Reply(job.tag, job.method)
        if job.aborted:
            reply.error(Code.TRANSACTION_ABORTED, record=False)
        elif job.error is not None:
            reply.error(job.error.code)
        else:
            assert job.command is not None
            self._run(job.command, job.plan, reply)
        self._serious(reply)  # before the ``%``: a command sent after it is not pending
        self._finish(job.tag, reply.lines, job.plan)

    def _run(self, cmd: Command, plan: FaultPlan, reply: Reply) -> None:
        if cmd.method not in MOVING or not self.state.in_session or self._refusal(cmd.method):
            self._answer(cmd, reply)
            return
        self.machine.look()
        with self._state_lock:
            if self._refusal(cmd.method):  # the platform struck the ball just now: the session is in error
                reply.refuse()
                return
            try:
                motion = self.handlers.motion_for(cmd, reply, plan)
            except ArgumentError as err:
                reply.error(err.code)
                return
        if motion is None:
            return
        machine = self.machine
        with machine.motion_lock:
            with machine.stop_lock:
                if self._abort_asked:
                    reply.error(Code.TRANSACTION_ABORTED, record=False)
                    return
                machine.motion_stop.clear()
            machine.user_enabled = False  # 6.3.2.4: moving implies DisableUser()
            try:
                machine.run(motion, self._stop.wait)
            except MotionStopped as stopped:
                log.info("cmm_sim.motion_stopped", tag=cmd.tag, reason=stopped.reason)
                emergency = stopped.reason == "emergency"
                reply.error(Code.EMERGENCY_STOP if emergency else Code.TRANSACTION_ABORTED, record=emergency)
                return
        if cmd.method == Method.CHANGE_TOOL:
            self._report_now()  # 6.3.2.7: a virtual move of the tool is reported too
        self.handlers.report(motion, reply)

    # ------------------------------------------------------------------ events

    def wants_moves(self) -> bool:
        return self.state.daemon is not None

    def moved(self, position: np.ndarray, dt: float) -> None:
        """The machine moved (any link's motion): OnMoveReportE's daemon reports when due (6.3.2.7)."""
        daemon = self.state.daemon
        if daemon is None:
            return
        daemon.since_s += dt
        if daemon.since_s < REPORT_INTERVAL_S - TIME_TOL_S:
            return
        report = daemon.report
        moved = float(np.linalg.norm(position - daemon.last_mm))
        due = (report.time_s is None and report.dis_mm is None) or \
            (report.time_s is not None and daemon.since_s >= report.time_s - TIME_TOL_S) or \
            (report.dis_mm is not None and moved >= report.dis_mm)
        if due:
            self._emit_report(position)

    def _report_now(self) -> None:
        with self.machine.lock:
            position = self.machine.position_mm.copy()
        if self.state.daemon is not None:
            self._emit_report(position)

    def _emit_report(self, position: np.ndarray) -> None:
        daemon = self.state.daemon
        if daemon is None:
            return
        daemon.since_s, daemon.last_mm = 0.0, position.copy()
        items = daemon.report.items or ("X", "Y", "Z")
        data = ", ".join(measured_item(item, self.machine, position, None) for item in items)
        self._write_event(line(daemon.tag, Marker.DATA, data))

    def _on_machine_event(self, code: Code, where: str) -> None:
        """An unsolicited error of the machine (an emergency stop, a platform that struck the ball): ``E0000 !``."""
        if not self.state.in_session:
            return
        reply = Reply(SERVER_EVENT_TAG, where)
        reply.error(code)
        self._serious(reply)
        self._write_event(reply.lines[0])

    def close(self) -> None:
        """The link ended: stop the worker (a motion it runs is stopped), forget the daemons."""
        self._closed.set()
        with self._cv:
            if self._current is not None:
                self.machine.request_stop("abort")
            self._cv.notify_all()
        self._worker.join(ABORT_WAIT_S)
        self.state.daemon = None
        for listeners, own in ((self.machine.move_listeners, self),
                               (self.machine.event_listeners, self._on_machine_event)):
            if own in listeners:
                listeners.remove(own)
