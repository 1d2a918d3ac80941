"""The engine: executes a procedure's messages against devices, journaling each result before going on.

Devices (`procedures.station.Devices`) hold a `drivers.controller.base.ControllerInterface`, a
`drivers.controller.modbus.ControllerParams`, the measuring instrument (`drivers.instrument.PoseInstrument`: a CMM
or a laser tracker, each keeping its own alignment to the base) and the robot. Short link drop-outs are ridden
through (`procedures.link_guard.LinkGuard`); a fault, a link that stays down or an operator abort stops motion, keeps
the journal and raises `RunInterrupted` with the way to resume. An optional observer (the operator panel) is told of
every message, result, pause and stop.

A laser tracker set up again during the run starts a new station (``drivers.tracker.station``): its rows say their
``station`` and the first row of each new one its ``station_change``, journaled too as a ``station_change`` event; a
resumed run continues the count from the journal's last row. A tracker moved farther than its searches reach
(``TrackerMoved``) stops an unattended run; an attended one asks the operator to set it up near its place and
measures the pose again.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import signal
import threading
import time
from collections.abc import Callable, Generator, Iterator
from contextlib import AbstractContextManager
from typing import Any

import numpy as np
import structlog

from drivers.controller.modbus import CompensationBlock, ParameterSet
from drivers.instrument import MeasuredPose, TrackerMoved
from hilcal.protocols.controller_states import MOTION_STATES, ControllerState
from hilcal.protocols.registers import Capability
from procedures import messages as m
from procedures.journal import Journal
from procedures.link_guard import LinkGuard, LinksSection

log = structlog.get_logger(__name__)


EngineObserver = Callable[[str, dict[str, Any]], None]
"""Called as observer(kind, data) on the engine's thread: "started", "message" {message} before a message is
executed, "done" {message, result} after, "paused" {message}, "resumed" {message}, "held" {link, message, error},
"recovered" {link, message, held_s}, "stopped" {reason},
"ended". An observer's exceptions are logged and ignored; a KeyboardInterrupt it raises is a Ctrl-C."""


@contextlib.contextmanager
def _ctrl_c_noted() -> Iterator[list[bool]]:
    """While the procedure computes its next message (a model refit, an identification), a Ctrl-C is noted, not raised:
    a generator that an exception left cannot go on, so the pause waits for the next message, as at a device step.
    Only in the main thread with Python's own handler in place (a signal handler can be set nowhere else)."""
    noted: list[bool] = []
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield noted
        return

    def note(*_: Any) -> None:
        noted.append(True)

    note.notes_ctrl_c = True  # type: ignore[attr-defined]
    signal.signal(signal.SIGINT, note)
    try:
        yield noted
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def ctrl_c_is_the_runs(handler: Any) -> bool:
    """Whether Ctrl-C is the run's own: Python's default handler, or the engine noting it while the procedure
    computes (a pause sent then is taken at the next message)."""
    return handler is signal.default_int_handler or bool(getattr(handler, "notes_ctrl_c", False))


class RunInterrupted(RuntimeError):
    """The run stopped before completion (abort, device fault, lost device); the journal is kept."""


def params_sha256(params: ParameterSet, compensation: CompensationBlock | None = None) -> str:
    """The identity of an upload: the parameter set and, when one goes with it, the compensation block."""
    content = params.model_dump() if compensation is None else {"params": params.model_dump(),
                                                                 "compensation": compensation.model_dump()}
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()


def same_block(a: CompensationBlock | None, b: CompensationBlock) -> bool:
    """The same block up to float32 register rounding."""
    return a is not None and a.as_float32() == b.as_float32()


def same_params(a: ParameterSet, b: ParameterSet, tol_mm: float = 1e-3) -> bool:
    """Equal up to float32 register rounding."""
    va = np.concatenate([np.ravel(a.a_mm), np.ravel(a.b_mm), a.l0_mm])
    vb = np.concatenate([np.ravel(b.a_mm), np.ravel(b.b_mm), b.l0_mm])
    return bool(np.all(np.abs(va - vb) <= tol_mm))


class Engine:
    """Runs one procedure; `confirm` answers prompts (None = unattended, every prompt answered yes)."""

    def __init__(self, devices: Any, journal: Journal, *, confirm: Callable[[str], bool] | None = None,
                 on_measure: Callable[[dict], None] | None = None, move_timeout_s: float = 120.0,
                 observer: EngineObserver | None = None, links: LinksSection | None = None,
                 approach_mm: float = 0.5, on_prompt: Callable[[m.Prompt], None] | None = None,
                 asking: Callable[[], AbstractContextManager[Any]] | None = None) -> None:
        self.devices = devices
        self.on_prompt = on_prompt
        """Called with a prompt before `confirm` asks it (a terminal prints the prompt's detail)."""
        self.asking = asking or contextlib.nullcontext
        """Entered while the operator reads a question (its detail included) and answers it: the terminal's live
        progress steps aside, so that nothing draws over the question."""
        self.move_timeout_s = move_timeout_s
        self.journal = journal
        self.confirm = confirm
        self.on_measure = on_measure
        self.observer = observer
        self.t0 = time.monotonic()
        self._reads_temperature: bool | None = None
        self.guard = LinkGuard(devices, journal, links, approach_mm=approach_mm, move_timeout_s=move_timeout_s,
                               publish=self._publish)

    def _publish(self, kind: str, **data: Any) -> None:
        if self.observer is not None:
            try:
                self.observer(kind, data)
            except Exception as e:
                log.warning("observer_failed", kind=kind, error=f"{type(e).__name__}: {e}")

    def run(self, procedure: Generator[Any, Any, Any]) -> Any:
        result: Any = None
        self._publish("started")
        try:
            while True:
                with _ctrl_c_noted() as noted:
                    msg = procedure.send(result)
                result = self._dispatch_pausable(msg, paused=bool(noted))
        except StopIteration as done:
            return done.value
        except KeyboardInterrupt:
            self._stop_motion("operator abort (Ctrl-C)")
            raise RunInterrupted("aborted by the operator") from None
        except RunInterrupted:
            self._stop_motion("procedure interrupted")
            raise
        except Exception as e:
            self._stop_motion(f"{type(e).__name__}: {e}")
            raise RunInterrupted(f"{type(e).__name__}: {e}") from e
        finally:
            self._publish("ended")

    def _dispatch_pausable(self, msg: object, paused: bool = False) -> Any:
        """Ctrl-C pauses: motion stops; an operator may go on (the message is executed again) or abort. `paused`: a
        Ctrl-C came while the procedure computed this message; the pause comes before it is executed.

        Every message is safe to repeat: a move goes to the same target, a journaled measurement is not
        taken twice, and an upload is settled by reading the live set back. Unattended runs abort.
        """
        while True:
            try:
                if paused:
                    paused = False
                    raise KeyboardInterrupt
                self._publish("message", message=msg)
                result = self.guard.run(msg, self._dispatch)
                self._publish("done", message=msg, result=result)
                return result
            except KeyboardInterrupt:
                self._stop_motion("paused by the operator (Ctrl-C)")
                self._publish("paused", message=type(msg).__name__)
                if self.confirm is None or not self._ask_continue():
                    raise RunInterrupted("aborted by the operator") from None
                self.journal.event("resumed_after_pause", message=type(msg).__name__)
                self._publish("resumed", message=type(msg).__name__)
                if isinstance(msg, m.MoveLegs | m.Measure | m.Settle):
                    self._on_enable(m.Enable())

    def _ask_continue(self) -> bool:
        try:
            with self.asking():
                return bool(self.confirm("Paused: motion stopped. Continue the run?"))
        except (KeyboardInterrupt, EOFError):
            return False

    def _stop_motion(self, reason: str) -> None:
        self.journal.event("interrupted", reason=reason)
        log.error("run_interrupted", reason=reason)
        self._publish("stopped", reason=reason)
        try:
            self.devices.controller.stop()
        except Exception as e:
            log.warning("stop_failed", error=str(e))

    def _dispatch(self, msg: object) -> Any:
        handler = getattr(self, f"_on_{type(msg).__name__.lower()}", None)
        if handler is None:
            raise TypeError(f"the engine does not know message {msg!r}")
        return handler(msg)

    def _on_prompt(self, msg: m.Prompt) -> bool:
        answer = True
        if self.confirm is not None:
            with self.asking():
                if self.on_prompt is not None:
                    self.on_prompt(msg)
                answer = self.confirm(msg.text)
        self.journal.event("prompt", key=msg.key, text=msg.text, answer=answer, unattended=self.confirm is None)
        if not answer:
            raise RunInterrupted(f"operator declined: {msg.text}")
        return True

    def _on_readparams(self, msg: m.ReadParams) -> tuple[ParameterSet, dict]:
        key = f"params:{msg.key}"
        stored = self.journal.step(key)
        if stored is None:
            identity = self.devices.params.read_identity()
            live = self.devices.params.read_live()
            block = self.devices.params.read_live_compensation() if identity.compensation else None
            stored = {"params": live.model_dump(), "offsets_only": identity.offsets_only,
                      "capabilities": int(identity.capabilities),
                      "compensation": None if block is None else block.model_dump()}
            self.journal.set_step(key, stored)
        return ParameterSet.model_validate(stored["params"]), stored

    def _on_readlegs(self, msg: m.ReadLegs) -> np.ndarray:
        return np.asarray(self.devices.controller.feedback().lengths_mm, dtype=float)

    def _on_preparecmm(self, msg: m.PrepareCmm) -> None:
        instrument = self.devices.instrument
        instrument.prepare()
        last = self.journal.last_measurement()
        if last is not None:  # a resumed run: the tracker's station count goes on
            instrument.continue_from(last["detail"])
        self.journal.event(f"{instrument.link}_ready")

    def _on_enable(self, msg: m.Enable) -> None:
        if self.devices.controller.state not in MOTION_STATES:
            self.devices.controller.enable()
        self.journal.event("enable")

    def _on_disable(self, msg: m.Disable) -> None:
        if self.devices.controller.state != ControllerState.DISABLED:
            self.devices.controller.disable()
        self.journal.event("disable")

    def _on_movelegs(self, msg: m.MoveLegs) -> np.ndarray:
        reached = self.devices.controller.move_legs(np.array(msg.lengths_mm), self.move_timeout_s)
        log.debug("moved", label=msg.label)
        return np.asarray(reached, dtype=float)

    def _on_settle(self, msg: m.Settle) -> None:
        time.sleep(msg.seconds)

    def _leg_temperature_c(self) -> float | None:
        """The controller's leg-temperature reading (register map 1.1 with TEMPERATURE_READING), else None."""
        if self._reads_temperature is None:
            caps = self.devices.params.read_identity().capabilities
            self._reads_temperature = Capability.TEMPERATURE_READING in caps
        return self.devices.params.read_temperature_c() if self._reads_temperature else None

    def _on_measure(self, msg: m.Measure) -> dict:
        row = self.journal.measurement(msg.phase, msg.index)
        if row is not None:
            return row
        temperature_c = self._leg_temperature_c()
        legs = np.asarray(self.devices.controller.feedback().lengths_mm, dtype=float)
        expected = np.array(msg.cmd_pose if msg.expected_pose is None else msg.expected_pose)
        cov = None if msg.pose_cov is None else np.reshape(msg.pose_cov, (6, 6))
        pm = self._measure_pose(msg, expected, cov)
        detail = {"sphere_fit_rms_mm": pm.registration_rms_mm, **pm.extra}
        if temperature_c is not None:
            detail["temp_c"] = temperature_c
        row = self.journal.add_measurement(msg.phase, msg.index, time.monotonic() - self.t0, np.array(msg.cmd_pose),
                                           legs, np.asarray(pm.pose, dtype=float), detail)
        log.info("measured", phase=msg.phase, index=msg.index)
        if "station_change" in detail:
            self.journal.event("station_change", phase=msg.phase, index=msg.index, **detail["station_change"])
        if self.on_measure is not None:
            self.on_measure(row)
        return row

    def _measure_pose(self, msg: m.Measure, expected: np.ndarray, cov: np.ndarray | None) -> MeasuredPose:
        """The instrument's pose; a tracker moved beyond its searches stops an unattended run, and at an attended one
        the operator sets it up near its place and the pose is measured again (or declines: the run stops)."""
        instrument = self.devices.instrument
        while True:
            try:
                return instrument.measure_pose(self.devices.robot, expected, cov)
            except TrackerMoved as moved:
                self.journal.event("tracker_moved", phase=msg.phase, index=msg.index, reason=str(moved))
                if self.confirm is None:
                    raise
                self._on_prompt(m.Prompt("tracker_moved", f"{moved}. Set the tracker up again near that place now "
                                         "(its monuments are searched for again): measure the pose again?"))
                instrument.expect_move()

    def _on_recall(self, msg: m.Recall) -> list[dict]:
        return self.journal.measurements(msg.phases)

    def _on_checkpoint(self, msg: m.Checkpoint) -> None:
        self.journal.set_step(f"checkpoint:{msg.label}", msg.data or {})

    def _live_pair(self, with_block: bool) -> tuple[ParameterSet, CompensationBlock | None]:
        client = self.devices.params
        return client.read_live(), client.read_live_compensation() if with_block else None

    def _on_upload(self, msg: m.Upload) -> dict:
        """Idempotent across a crash: a started upload is settled by reading the live set (and block) back."""
        params: ParameterSet = msg.params
        block: CompensationBlock | None = msg.compensation  # type: ignore[assignment]
        sha = params_sha256(params, block)
        state = self.journal.step("upload")
        client = self.devices.params
        if state is not None and state["sha256"] == sha and state["outcome"] in ("started", "committed"):
            live, live_block = self._live_pair(block is not None)
            previous_block = state.get("previous_compensation")
            if same_params(live, params) and (block is None or same_block(live_block, block)):
                state = {**state, "outcome": "committed"}
                self.journal.set_step("upload", state)
            elif not (same_params(live, ParameterSet.model_validate(state["previous"])) and (
                    block is None or previous_block is None or
                    same_block(live_block, CompensationBlock.model_validate(previous_block)))):
                raise RunInterrupted("the controller's live set is neither the previous nor the new one: "
                                     "check the controller before going on")
            else:
                state = None
        if state is None:
            previous, previous_block = self._live_pair(block is not None)
            started = {"sha256": sha, "outcome": "started", "previous": previous.model_dump(),
                       "previous_compensation": None if previous_block is None else previous_block.model_dump()}
            self.journal.set_step("upload", started)
            record = client.upload(params, save=False, compensation=block)
            state = {**started, "outcome": "committed", "record": record.model_dump(mode="json")}
            self.journal.set_step("upload", state)
        if msg.save and state["outcome"] != "saved":
            save_record = client.save()
            state = {**state, "outcome": "saved", "save_record": save_record.model_dump(mode="json")}
            self.journal.set_step("upload", state)
        self.journal.event("upload", outcome=state["outcome"], sha256=sha)
        return state
