"""The engine asks its questions inside the `asking` context (the terminal's bar steps aside), and the bar's
`bar_aside` takes the live display off a terminal's screen and back.

The whole run at a terminal, read from an emulated screen, is tests/cli/run/test_run_terminal.py."""

from __future__ import annotations

import contextlib
import io
import os
import signal
import threading

import pyte
from rich.console import Console
from rich.progress import Progress

from hilcal.kinematics import Geometry, inverse_kinematics
from procedures import messages as m
from procedures.engine import Engine
from procedures.journal import Journal
from procedures.run_progress import bar_aside

DETAIL = {"diff": []}


def _questions():
    yield m.Prompt("spheres", "Spheres mounted?")
    yield m.Prompt("upload", "Upload?", DETAIL)
    return "done"


class _Log:
    """What happened in order, and whether the `asking` context was held at the time."""

    def __init__(self) -> None:
        self.events: list[tuple[str, bool]] = []
        self.held = False

    @contextlib.contextmanager
    def asking(self):
        self.events.append(("aside", self.held))
        self.held = True
        try:
            yield
        finally:
            self.held = False
            self.events.append(("back", self.held))

    def confirm(self, text: str) -> bool:
        self.events.append((f"asked {text}", self.held))
        return True

    def detail(self, prompt: m.Prompt) -> None:
        self.events.append((f"detail {prompt.key}", self.held))


def test_each_prompt_and_its_detail_are_asked_with_the_bar_aside(devices, tmp_path):
    log = _Log()
    with Journal(tmp_path / "j.sqlite") as journal:
        engine = Engine(devices, journal, confirm=log.confirm, on_prompt=log.detail, asking=log.asking)
        assert engine.run(_questions()) == "done"
    assert log.events == [("aside", False), ("detail spheres", True), ("asked Spheres mounted?", True), ("back", False),
                          ("aside", False), ("detail upload", True), ("asked Upload?", True), ("back", False)]


def test_unattended_nothing_is_asked_and_the_bar_stays(devices, tmp_path):
    log = _Log()
    with Journal(tmp_path / "j.sqlite") as journal:
        Engine(devices, journal, confirm=None, on_prompt=log.detail, asking=log.asking).run(_questions())
        assert [e["data"]["unattended"] for e in journal.events("prompt")] == [True, True]
    assert log.events == []


def test_the_pause_question_is_asked_with_the_bar_aside(devices, tmp_path):
    robot = devices.robot
    home = inverse_kinematics(Geometry.nominal(robot), robot.home)

    def moves():
        yield m.Enable()
        yield m.MoveLegs(m.as_tuple(home + 40.0), "out")
        yield m.MoveLegs(m.as_tuple(home), "back")

    log = _Log()
    with Journal(tmp_path / "j.sqlite") as journal:
        engine = Engine(devices, journal, confirm=log.confirm, asking=log.asking)
        threading.Timer(0.3, lambda: os.kill(os.getpid(), signal.SIGINT)).start()
        engine.run(moves())
        assert journal.count_events("resumed_after_pause") == 1
    assert log.events == [("aside", False), ("asked Paused: motion stopped. Continue the run?", True), ("back", False)]


def _bar(terminal: bool) -> tuple[Progress, io.StringIO]:
    screen = io.StringIO()
    console = Console(file=screen, force_terminal=terminal, width=80)
    return Progress(console=console, auto_refresh=False), screen


def _screen(written: str) -> list[str]:
    """The terminal's screen after `written` (a terminal emulator's view)."""
    screen = pyte.Screen(80, 10)
    pyte.Stream(screen).feed(written.replace("\n", "\r\n"))
    return [line.rstrip() for line in screen.display if line.strip()]


def test_bar_aside_erases_the_bar_on_a_terminal_and_draws_it_again_below_the_answer():
    bar, written = _bar(terminal=True)
    with bar:
        task = bar.add_task("measuring poses", total=10)
        bar.update(task, completed=3)
        bar.console.print("the estimate")
        bar.refresh()
        assert [line.split()[:2] for line in _screen(written.getvalue())] == [["the", "estimate"],
                                                                               ["measuring", "poses"]]
        with bar_aside(bar):
            assert not bar.live.is_started
            assert _screen(written.getvalue()) == ["the estimate"]
            written.write("Go on? [y/N]: y\n")  # the question and its answer, echoed by the terminal
        assert bar.live.is_started and not bar.live.transient
        shown = _screen(written.getvalue())
    assert shown[:2] == ["the estimate", "Go on? [y/N]: y"]
    assert len(shown) == 3 and shown[2].startswith("measuring poses") and "30%" in shown[2]


def test_bar_aside_does_nothing_without_a_terminal():
    bar, screen = _bar(terminal=False)
    with bar:
        bar.add_task("measuring poses", total=10)
        with bar_aside(bar):
            assert bar.live.is_started
            assert screen.getvalue() == ""


def test_a_ctrl_c_while_the_procedure_computes_pauses_before_its_next_message(devices, tmp_path):
    """A Ctrl-C that lands in the procedure's own work (a model refit between two poses) is kept for the next
    message: the run pauses there and goes on, instead of aborting (a generator an exception left cannot go on)."""
    import time

    robot = devices.robot
    home = inverse_kinematics(Geometry.nominal(robot), robot.home)

    def thinking():
        yield m.Enable()
        os.kill(os.getpid(), signal.SIGINT)  # the operator presses Ctrl-C while the procedure computes
        time.sleep(0.05)
        yield m.MoveLegs(m.as_tuple(home), "home")
        return "went on"

    log = _Log()
    with Journal(tmp_path / "j.sqlite") as journal:
        engine = Engine(devices, journal, confirm=log.confirm, asking=log.asking)
        assert engine.run(thinking()) == "went on"
        assert [e["data"]["message"] for e in journal.events("resumed_after_pause")] == ["MoveLegs"]
    assert ("asked Paused: motion stopped. Continue the run?", True) in log.events
