"""The link guard inside the engine, against the in-process simulated devices over their real transports:
a heartbeat that stops for a moment mid-move is ridden through and the pose re-taken from its approach point; one
that stays away ends the run; a fault seen when the link returns ends it without moving; a CMM silent beyond the
driver's own resends is retried by the engine; a Modbus connection dropped during the upload is retried and the
upload stays whole."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from drivers.cmm.ippdme import IppDmeConfig
from drivers.controller.modbus import ParameterSet
from hilcal.kinematics import Geometry, inverse_kinematics
from hilcal.protocols.controller_states import FaultCode
from procedures import messages as m
from procedures.engine import Engine, RunInterrupted
from procedures.journal import Journal
from procedures.link_guard import LinksSection
from procedures.station import open_devices, station_from_channels
from sim_devices.sim_config import SimConfig, SimControllerConfig
from sim_devices.simulator import start_sim


@pytest.fixture
def sim():
    with start_sim(SimConfig(controller=SimControllerConfig(time_scale=1.0))) as handle:
        yield handle


@pytest.fixture
def devices(sim):
    with open_devices(station_from_channels(sim.channels())) as devs:
        yield devs


def _moves(robot, out_mm: float = 40.0):
    home = inverse_kinematics(Geometry.nominal(robot), robot.home)
    yield m.PrepareCmm()
    yield m.Enable()
    yield m.MoveLegs(m.as_tuple(home + out_mm), "out")
    reached = yield m.MoveLegs(m.as_tuple(home), "back")
    row = yield m.Measure("measure", 0, m.as_tuple(robot.home))
    return reached, row


def _silence(sim, after_s: float, for_s: float) -> threading.Timer:
    """Stop every heartbeat of the simulated controller after `after_s` for `for_s` (its CAN servers' switch)."""
    faults = sim.controller_servers.slcan.faults

    def off() -> None:
        faults.set_heartbeat(False)
        threading.Timer(for_s, faults.set_heartbeat, (True,)).start()

    timer = threading.Timer(after_s, off)
    timer.start()
    return timer


def _kinds(journal: Journal) -> list[str]:
    return [e["kind"] for e in journal.events("link_hold", "link_recovered", "link_retake", "link_lost",
                                               "link_unsafe", "link_position_checked")]


def test_a_short_heartbeat_gap_mid_move_is_ridden_through(sim, devices, tmp_path):
    home = inverse_kinematics(Geometry.nominal(devices.robot), devices.robot.home)
    with Journal(tmp_path / "j.sqlite") as journal:
        engine = Engine(devices, journal, approach_mm=2.0)
        _silence(sim, 0.4, 0.4)  # the 40 mm move takes about 0.8 s at 50 mm/s
        reached, row = engine.run(_moves(devices.robot))
        np.testing.assert_allclose(reached, home, atol=0.01)
        assert row["phase"] == "measure"
        kinds = _kinds(journal)
        assert kinds[:3] == ["link_hold", "link_retake", "link_recovered"] or \
            kinds[:3] == ["link_hold", "link_recovered", "link_retake"], kinds
        held = [e["data"]["held_s"] for e in journal.events("link_recovered")]
        assert 0.2 < held[0] < 1.0


def test_a_move_near_the_lower_limit_is_re_taken_within_the_travel(tmp_path):
    """An approach point 1 mm above the lower leg limit (the plan keeps them at least that far) interrupted by a gap:
    the re-take's own approach point stays at the limit instead of 2 mm below it (a setpoint the controller refuses,
    which stopped the run)."""
    with start_sim(SimConfig(controller=SimControllerConfig(time_scale=10.0))) as fast, \
            open_devices(station_from_channels(fast.channels())) as devs, Journal(tmp_path / "j.sqlite") as journal:
        lowest_mm = devs.robot.leg_limits[0]
        target = np.full(6, lowest_mm + 1.0)

        def moves():
            yield m.Enable()
            return (yield m.MoveLegs(m.as_tuple(target), "pose 1 approach"))

        _silence(fast, 0.4, 0.4)  # the 500 mm move takes about 1 s at 10 x 50 mm/s
        reached = Engine(devs, journal, approach_mm=2.0).run(moves())
        np.testing.assert_allclose(reached, target, atol=0.01)
        assert "link_retake" in _kinds(journal) and "link_lost" not in _kinds(journal)


def test_a_heartbeat_that_stays_away_ends_the_run_without_motion(sim, devices, tmp_path):
    peer_stats = sim.controller_servers.slcan.peer.stats
    with Journal(tmp_path / "j.sqlite") as journal:
        engine = Engine(devices, journal)
        _silence(sim, 0.4, 8.0)  # far beyond the 1 s grace period, however late a busy machine notices the gap
        sent_before = threading.Event()
        counts: list[int] = []

        def watch() -> None:
            sent_before.wait(0.6)  # 0.2 s into the silence: the host knows the link is down
            counts.append(peer_stats.rx_by_name["SetpointL12"])

        threading.Thread(target=watch, daemon=True).start()
        with pytest.raises(RunInterrupted, match=r"controller link lost.*grace period"):
            engine.run(_moves(devices.robot, 80.0))
        assert peer_stats.rx_by_name["SetpointL12"] == counts[0], "no setpoint after the link went down"
        assert _kinds(journal) == ["link_hold", "link_lost"]


def test_a_fault_seen_when_the_link_returns_ends_the_run(sim, devices, tmp_path):
    with Journal(tmp_path / "j.sqlite") as journal:
        engine = Engine(devices, journal)
        _silence(sim, 0.4, 0.5)
        threading.Timer(0.5, sim.controller.inject_fault, (FaultCode.DRIVE,)).start()
        with pytest.raises(RunInterrupted, match="FAULT"):
            engine.run(_moves(devices.robot))
        assert "link_unsafe" in _kinds(journal) and "link_retake" not in _kinds(journal)


def test_a_cmm_silent_beyond_the_drivers_resends_is_retried(sim, tmp_path):
    station = station_from_channels(sim.channels())
    quick = station.model_copy(update={  # 0.3 s per unanswered command: the same rules, sooner
        "cmm": station.cmm.model_copy(update={"ippdme": IppDmeConfig(ack_timeout_s=0.3, abort_timeout_s=0.3)}),
        "links": LinksSection(cmm_wait_s=0.1)})
    with open_devices(quick) as devices, Journal(tmp_path / "j.sqlite") as journal:
        engine = Engine(devices, journal)
        engine.run(iter_once(m.PrepareCmm()))
        # the measurement's first command (a query: SetProp) is asked 1 + query_retries (2) times, all silent: the
        # engine holds and measures again; that one's first command meets the fourth silence and is asked again
        sim.cmm_server.faults.inject("silence", count=4)
        row = engine.run(iter_once(m.Measure("measure", 0, m.as_tuple(devices.robot.home))))
        assert row["index"] == 0 and len(journal.measurements(("measure",))) == 1
        cmm = [e["data"] for e in journal.events("link_hold") if e["data"]["link"] == "cmm"]
        assert len(cmm) == 1 and "Timeout" in cmm[0]["error"]


def iter_once(msg: object):
    return (yield msg)


def test_a_modbus_drop_during_the_upload_is_retried_and_the_set_stays_whole(sim, devices, tmp_path):
    live = devices.params.read_live()
    new = ParameterSet(a_mm=live.a_mm, b_mm=live.b_mm, l0_mm=(np.array(live.l0_mm) + 0.25).tolist())
    with Journal(tmp_path / "j.sqlite") as journal:
        engine = Engine(devices, journal)
        sim.controller_servers.modbus.faults.drop_connection_at_write(3)

        def plan():
            yield m.Disable()
            return (yield m.Upload(new, False))

        state = engine.run(plan())
        assert state["outcome"] == "committed"
        assert [e["data"]["link"] for e in journal.events("link_hold")] == ["modbus"]
        np.testing.assert_allclose(devices.params.read_live().l0_mm, new.l0_mm, atol=1e-4)
