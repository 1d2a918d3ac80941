"""The engine against the in-process simulated devices: Ctrl-C pauses, an operator continues or aborts."""

from __future__ import annotations

import os
import signal
import threading

import numpy as np
import pytest

from hilcal.kinematics import Geometry, inverse_kinematics
from procedures import messages as m
from procedures.engine import Engine, RunInterrupted
from procedures.journal import Journal


def _procedure(robot):
    home = inverse_kinematics(Geometry.nominal(robot), robot.home)
    yield m.PrepareCmm()
    yield m.Enable()
    yield m.MoveLegs(m.as_tuple(home + 40.0), "out")
    yield m.MoveLegs(m.as_tuple(home), "back")
    row = yield m.Measure("measure", 0, m.as_tuple(robot.home))
    yield m.Disable()
    return row


def _interrupt_after(seconds: float) -> threading.Timer:
    timer = threading.Timer(seconds, lambda: os.kill(os.getpid(), signal.SIGINT))
    timer.start()
    return timer


def test_ctrl_c_pauses_and_the_operator_continues(devices, tmp_path):
    asked: list[str] = []
    with Journal(tmp_path / "j.sqlite") as journal:
        engine = Engine(devices, journal, confirm=lambda text: asked.append(text) or True)
        _interrupt_after(0.3)
        row = engine.run(_procedure(devices.robot))
        assert any("Paused" in text for text in asked)
        assert row["phase"] == "measure"
        np.testing.assert_allclose(row["meas"][:3], devices.robot.home[:3], atol=5.0)
        kinds = [r[0] for r in journal._db.execute("SELECT kind FROM events").fetchall()]
        assert "interrupted" in kinds and "resumed_after_pause" in kinds


def test_ctrl_c_unattended_stops_motion_and_aborts(devices, tmp_path):
    with Journal(tmp_path / "j.sqlite") as journal:
        engine = Engine(devices, journal, confirm=None)
        _interrupt_after(0.3)
        with pytest.raises(RunInterrupted, match="aborted by the operator"):
            engine.run(_procedure(devices.robot))
        assert journal.measurements(("measure",)) == []
        assert devices.controller.state.name in ("ENABLED", "IN_POSITION")
