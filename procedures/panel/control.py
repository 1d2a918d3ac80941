"""The operator's controls for one run: questions answered on the page or at the terminal, pause/continue/abort.

Whichever answer comes first wins; the other side is told. Every answer is journaled with its time, the
operator named at start and where it came from (page, terminal or --yes). Pause does exactly what Ctrl-C
does: SIGINT to the engine's thread, so the engine stops motion and asks whether to continue; continue
and abort answer that question. A pause asked for between two messages (during the identification, say)
is delivered when the engine starts the next message. The upload approval needs the page to send back
the SHA-256 of the parameter set it showed: an approval can only be for the set the operator read.
"""

from __future__ import annotations

import datetime as dt
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

from procedures import messages as m
from procedures.approval import approval_lines
from procedures.engine import ctrl_c_is_the_runs

YES = ("y", "yes")
NO = ("n", "no")


class PanelRequestError(ValueError):
    """A page request that cannot be honoured now; nothing changed. `status` is the HTTP status to answer."""

    def __init__(self, message: str, status: int = 409) -> None:
        super().__init__(message)
        self.status = status


class NotStarted(RuntimeError):
    """The operator declined to start the run."""


@dataclass
class Question:
    """One question to the operator; `answer` None while open."""

    id: int
    kind: str
    key: str
    text: str
    detail: dict[str, Any] | None
    asked_at: float
    answer: bool | None = None
    operator: str | None = None
    via: str | None = None
    client: str | None = None
    answered_at: float | None = None
    closed: str | None = None

    def public(self) -> dict[str, Any]:
        return {**asdict(self), "open": self.answer is None and self.closed is None}


def _iso(t: float) -> str:
    return dt.datetime.fromtimestamp(t, dt.UTC).isoformat(timespec="milliseconds")


class OperatorControl:
    """Answers the engine's questions (its `confirm`) from the page or the terminal; pause, continue, abort.

    `on_engine_event` must be registered as an engine observer before the run starts. `journal_event` is
    called on the engine's thread with each answer (normally `Journal.event`).
    """

    def __init__(self, live: Any, *, operator: str | None = None, yes: bool = False,
                 say: Callable[[str], None] = print, main_thread: threading.Thread | None = None) -> None:
        self.live = live
        self.operator = operator
        self.yes = yes
        self.say = say
        self.journal_event: Callable[..., None] | None = None
        self._main = main_thread or threading.main_thread()
        self._cond = threading.Condition()
        self._question: Question | None = None
        self._next_id = 1
        self._prompt: m.Prompt | None = None
        self._engine_active = False
        self._dispatching = False
        self._paused = False
        self._pause_pending: str | None = None
        self._pause_via: str | None = None
        self._abort_pending = False
        self.start_plan: dict[str, Any] | None = None
        """The measurement plan chosen on the start form (None: as the command line asked)."""
        self._check_plan: Callable[[dict[str, Any]], dict[str, Any]] | None = None

    # ------------------------------------------------------------------ engine side (engine thread)

    def on_engine_event(self, kind: str, data: dict[str, Any]) -> None:
        deliver_pause = False
        with self._cond:
            if kind == "started":
                self._engine_active = True
            elif kind == "ended":
                self._engine_active = self._dispatching = self._paused = False
                self._pause_pending = None
            elif kind == "message":
                self._dispatching = True
                if isinstance(data["message"], m.Prompt):
                    self._prompt = data["message"]
                deliver_pause = self._pause_pending is not None
                self._pause_pending = None
            elif kind == "done":
                self._dispatching = False
            elif kind == "paused":
                self._dispatching, self._paused = False, True
            elif kind == "resumed":
                self._paused = False
                self._pause_via = None
        if deliver_pause:
            raise KeyboardInterrupt  # the engine treats it exactly as Ctrl-C at the start of this message

    def confirm(self, text: str) -> bool:
        """The engine's `confirm`: a procedure prompt, or after Ctrl-C/pause whether to continue."""
        with self._cond:
            paused, prompt = self._paused, self._prompt
            pause_via, abort = self._pause_via, self._abort_pending
        if paused:
            if abort:
                return self._record(self._new("pause", "pause", text, None), False, pause_via or "page", None)
            if self.yes and pause_via is None:
                return self._record(self._new("pause", "pause", text, None), False, "--yes", None)
            return self._ask("pause", "pause", text, {"paused_by": pause_via or "Ctrl-C at the terminal"})
        key = prompt.key if prompt is not None and prompt.text == text else "question"
        detail = prompt.detail if prompt is not None and prompt.text == text else None
        kind = "upload" if key == "upload" else "prompt"
        if self.yes:
            return self._record(self._new(kind, key, text, detail), True, "--yes", None)
        return self._ask(kind, key, text, detail)

    def wait_start(self, text: str, plan: dict[str, Any] | None = None,
                   check_plan: Callable[[dict[str, Any]], dict[str, Any]] | None = None) -> str:
        """Block until the operator starts the run (page or terminal); returns the operator's name.

        plan: the measurement plan the start form shows (``choosable``: a new run's plan can still change there);
        check_plan validates a plan chosen on the page (ValueError with the reason) and returns it normalized.
        """
        if self.yes:
            self._record(self._new("start", "start", text, None), True, "--yes", None)
            return self.operator or ""
        self._check_plan = check_plan if plan is not None and plan.get("choosable") else None
        if not self._ask("start", "start", text, {"operator": self.operator, "plan": plan}):
            raise NotStarted("the operator did not start the run")
        return self.operator or ""

    # ------------------------------------------------------------------ questions

    def _new(self, kind: str, key: str, text: str, detail: dict[str, Any] | None) -> Question:
        with self._cond:
            q = Question(self._next_id, kind, key, text, detail, time.time())
            self._next_id += 1
            return q

    def _ask(self, kind: str, key: str, text: str, detail: dict[str, Any] | None) -> bool:
        q = self._new(kind, key, text, detail)
        with self._cond:
            self._question = q
        self.live.set("prompt", q.public())
        self.live.note(f"question to the operator: {text.splitlines()[0]}")
        self.say(self._terminal_text(q))
        try:
            with self._cond:
                while q.answer is None:
                    self._cond.wait(0.25)
        except BaseException:
            with self._cond:
                q.closed = "interrupted"
                self._question = None
            self.live.set("prompt", q.public())
            raise
        with self._cond:
            self._question = None
        if q.via != "terminal":
            self.say(f"-> answered {'yes' if q.answer else 'no'} {q.via and 'on the ' + q.via} by {q.operator}")
        return self._record(q, bool(q.answer), q.via or "page", q.client, answered=True)

    def _record(self, q: Question, answer: bool, via: str, client: str | None, answered: bool = False) -> bool:
        if not answered:
            q.answer, q.via, q.client, q.answered_at = answer, via, client, time.time()
            q.operator = self.operator
        self.live.set("prompt", q.public())
        self.live.note(f"{q.key}: {'yes' if answer else 'no'} ({via}, {q.operator or 'no operator named'})")
        if self.journal_event is not None:
            self.journal_event("operator_answer", key=q.key, question=q.kind, text=q.text, answer=answer,
                               operator=q.operator, via=via, client=client, asked_at=_iso(q.asked_at),
                               answered_at=_iso(q.answered_at or time.time()))
        return answer

    def _terminal_text(self, q: Question) -> str:
        lines = [f"\n[panel] {q.text}"]
        if q.kind == "upload" and q.detail:
            lines += approval_lines(q.detail)
        if q.kind == "start":
            lines.append("Type the operator's name and Enter to start" +
                         (f" (Enter alone: {self.operator})" if self.operator else "") + ", or answer on the panel.")
        else:
            lines.append("Answer y or n here, or on the panel.")
        return "\n".join(lines)

    def _resolve_locked(self, q: Question, answer: bool, via: str, client: str | None, operator: str | None) -> None:
        if operator:
            self.operator = operator
        q.answer, q.via, q.client, q.answered_at, q.operator = answer, via, client, time.time(), self.operator
        self._cond.notify_all()

    # ------------------------------------------------------------------ page and terminal (their threads)

    def answer(self, question_id: int, answer: bool, *, client: str | None = None, operator: str | None = None,
               confirm_sha256: str | None = None, plan: Any = None) -> dict[str, Any]:
        """An answer from the page; PanelRequestError if that question is not the open one (or, starting, if the
        plan chosen on the form cannot make a run: nothing changes then)."""
        with self._cond:
            q = self._question
            if q is None or q.id != question_id or q.answer is not None:
                raise PanelRequestError("that question is no longer open (answered elsewhere or withdrawn)")
            name = (operator or "").strip() or None
            if q.kind == "start" and answer and not (name or self.operator):
                raise PanelRequestError("give the operator's name to start the run", 400)
            if q.kind == "start" and answer and plan is not None:
                self.start_plan = self._checked_plan(plan)
            if q.kind == "upload" and answer and confirm_sha256 != (q.detail or {}).get("new_sha256"):
                raise PanelRequestError("approving the upload needs the explicit confirmation of the parameter set "
                                        "shown (its SHA-256); nothing was uploaded", 400)
            self._resolve_locked(q, answer, "page", client, name if q.kind == "start" else None)
            return q.public()

    def _checked_plan(self, plan: Any) -> dict[str, Any]:
        if self._check_plan is None:
            raise PanelRequestError("this run's plan cannot change any more (a resumed run goes on as it started)", 400)
        if not isinstance(plan, dict) or not isinstance(plan.get("adaptive"), bool):
            raise PanelRequestError("'plan' must be an object with 'adaptive' true or false", 400)
        try:
            return self._check_plan(plan)
        except ValueError as e:
            raise PanelRequestError(f"the plan: {e}; nothing started", 400) from None

    def terminal_line(self, line: str) -> None:
        """A line typed at the terminal answers the open question, if any."""
        text = line.strip()
        with self._cond:
            q = self._question
            if q is None or q.answer is not None:
                return
            if q.kind == "start":
                if text.lower() in NO:
                    self._resolve_locked(q, False, "terminal", None, None)
                elif text.lower() in YES and self.operator:
                    self._resolve_locked(q, True, "terminal", None, None)
                elif text or self.operator:
                    self._resolve_locked(q, True, "terminal", None, text if text.lower() not in YES else None)
                else:
                    self.say("type the operator's name to start")
                return
            if text.lower() in YES + NO:
                self._resolve_locked(q, text.lower() in YES, "terminal", None, None)
            else:
                self.say("answer y or n")

    def pause(self, via: str = "page") -> None:
        """Exactly Ctrl-C: SIGINT to the engine's thread now, or at the start of its next message."""
        with self._cond:
            if not self._engine_active:
                raise PanelRequestError("the run is not running")
            if self._paused or self._pause_via is not None:
                raise PanelRequestError("the run is already paused")
            if not ctrl_c_is_the_runs(signal.getsignal(signal.SIGINT)):
                raise PanelRequestError("this process handles Ctrl-C itself; pause at the terminal", 503)
            self._pause_via = via
            if self._dispatching:
                signal.pthread_kill(self._main.ident, signal.SIGINT)  # type: ignore[arg-type]
            else:
                self._pause_pending = via
        self.live.note(f"pause requested on the {via}")

    def continue_run(self) -> None:
        with self._cond:
            q = self._question
            if q is None or q.kind != "pause":
                raise PanelRequestError("the run is not paused")
            self._resolve_locked(q, True, "page", None, None)

    def abort(self) -> None:
        """Ctrl-C and then 'do not continue': motion stops, the journal is kept, the run can be resumed."""
        with self._cond:
            q = self._question
            if q is not None and q.kind in ("pause", "start"):
                self._resolve_locked(q, False, "page", None, None)
                return
            if not self._engine_active:
                raise PanelRequestError("the run is not running")
            self._abort_pending = True
        try:
            self.pause("page")
        except PanelRequestError:
            if not self._paused:
                raise
