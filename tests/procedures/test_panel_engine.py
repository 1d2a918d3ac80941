"""The panel's pause, continue and abort against the engine and the in-process simulated devices, over HTTP."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import httpx2 as httpx
import numpy as np
import pytest

from hilcal.kinematics import Geometry, inverse_kinematics
from procedures import messages as m
from procedures.engine import Engine, RunInterrupted
from procedures.journal import Journal
from procedures.panel.session import PanelSession

COMMAND = {"X-Hilcal-Panel": "1"}


@pytest.fixture
def panel():
    session = PanelSession(port=0, operator="T. Tester", terminal_fd=None, say=lambda text: None)
    session.start()
    yield session
    session.close()


def _procedure(robot, think_s: float = 0.0):
    home = inverse_kinematics(Geometry.nominal(robot), robot.home)
    yield m.PrepareCmm()
    yield m.Enable()
    time.sleep(think_s)  # a computation between messages, like the identification
    yield m.MoveLegs(m.as_tuple(home + 40.0), "measure 1 transit")
    yield m.MoveLegs(m.as_tuple(home), "measure 1 target")
    row = yield m.Measure("measure", 0, m.as_tuple(robot.home))
    yield m.Disable()
    return row


def _wait(condition: Callable[[], bool], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def _legs_still(devices, seconds: float = 0.3) -> bool:
    a = np.asarray(devices.controller.feedback().lengths_mm)
    time.sleep(seconds)
    return bool(np.allclose(a, devices.controller.feedback().lengths_mm, atol=0.01))


def _operator(panel: PanelSession, actions: Callable[[httpx.Client], None]) -> tuple[threading.Thread, list]:
    errors: list = []

    def work() -> None:
        try:
            with httpx.Client(base_url=panel.url.rstrip("/"), headers=COMMAND, timeout=5) as client:
                actions(client)
        except BaseException as e:  # reported by the test
            errors.append(e)

    thread = threading.Thread(target=work)
    thread.start()
    return thread, errors


def _pause_question(panel: PanelSession) -> bool:
    prompt = panel.live.get("prompt")
    return prompt is not None and prompt["open"] and prompt["kind"] == "pause"


def _events(journal: Journal, kind: str) -> list:
    return journal._db.execute("SELECT data_json FROM events WHERE kind = ?", (kind,)).fetchall()


def test_pause_from_the_page_stops_motion_and_continue_finishes_the_move(devices, panel, tmp_path):
    seen: dict = {}

    def actions(client: httpx.Client) -> None:
        _wait(lambda: (panel.live.get("progress") or {}).get("activity", "").startswith("moving"))
        time.sleep(0.3)
        assert client.post("/api/pause").status_code == 200
        _wait(lambda: _pause_question(panel))
        seen["still"] = _legs_still(devices)
        seen["status"] = panel.live.get("run")["status"]
        assert client.post("/api/pause").status_code == 409  # already paused
        assert client.post("/api/continue").status_code == 200

    with Journal(tmp_path / "j.sqlite") as journal:
        panel.control.journal_event = journal.event
        engine = Engine(devices, journal, confirm=panel.confirm, observer=panel.observer)
        thread, errors = _operator(panel, actions)
        row = engine.run(_procedure(devices.robot))
        thread.join(10)
        assert not errors, errors
        assert seen == {"still": True, "status": "paused"}
        np.testing.assert_allclose(row["meas"][:3], devices.robot.home[:3], atol=5.0)
        answers = [r[0] for r in _events(journal, "operator_answer")]
        assert len(answers) == 1 and '"via": "page"' in answers[0] and '"answer": true' in answers[0]
        assert '"operator": "T. Tester"' in answers[0]
        assert len(_events(journal, "resumed_after_pause")) == 1


def test_abort_from_the_page_keeps_the_journal(devices, panel, tmp_path):
    def actions(client: httpx.Client) -> None:
        _wait(lambda: (panel.live.get("progress") or {}).get("activity", "").startswith("moving"))
        time.sleep(0.2)
        assert client.post("/api/abort").status_code == 200

    with Journal(tmp_path / "j.sqlite") as journal:
        panel.control.journal_event = journal.event
        engine = Engine(devices, journal, confirm=panel.confirm, observer=panel.observer)
        thread, errors = _operator(panel, actions)
        with pytest.raises(RunInterrupted, match="aborted by the operator"):
            engine.run(_procedure(devices.robot))
        thread.join(10)
        assert not errors, errors
        assert _legs_still(devices)
        (answer,) = [r[0] for r in _events(journal, "operator_answer")]
        assert '"answer": false' in answer and '"key": "pause"' in answer
        assert journal.measurements(("measure",)) == []
        assert len(_events(journal, "interrupted")) == 2  # the pause's motion stop, then the abort's


def test_a_pause_between_messages_is_taken_before_the_next_move(devices, panel, tmp_path):
    seen: dict = {}

    def actions(client: httpx.Client) -> None:
        _wait(lambda: (panel.live.get("progress") or {}).get("activity") == "servo on")
        time.sleep(0.2)  # the procedure is thinking: no message is being executed
        assert client.post("/api/pause").status_code == 200
        _wait(lambda: _pause_question(panel))
        home = inverse_kinematics(Geometry.nominal(devices.robot), devices.robot.home)
        seen["not_moved"] = bool(np.allclose(devices.controller.feedback().lengths_mm, home, atol=1.0))
        assert client.post("/api/continue").status_code == 200

    with Journal(tmp_path / "j.sqlite") as journal:
        panel.control.journal_event = journal.event
        engine = Engine(devices, journal, confirm=panel.confirm, observer=panel.observer)
        thread, errors = _operator(panel, actions)
        row = engine.run(_procedure(devices.robot, think_s=1.0))
        thread.join(10)
        assert not errors, errors
        assert seen == {"not_moved": True}
        assert row["phase"] == "measure"
