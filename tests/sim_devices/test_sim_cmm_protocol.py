"""The simulated CMM's protocol behaviour as I++ DME 1.4.3 states it: lines and tags (6.1.1, 6.2.1, 6.2.2), sessions
(6.3.1), the error state (6.2.5, 6.3.1.7), transactions in order with events at any time (6.2.3, 6.2.4), AbortE
during a running motion (6.3.1.5), OnMoveReportE (6.3.2.7), the emergency stop (9.5) and the machine shared by a pty
and a TCP link. Driven by a test client over real transports; motions that must take real time use time_scale 1.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
import pytest

from hilcal.robot import default_robot
from sim_devices.cmm.config import CmmServerConfig
from sim_devices.cmm.server import CmmServerHandle, start_cmm_server
from sim_devices.rig.config import RigConfig, load_errors
from sim_devices.rig.rig import SimulatedRig
from tests.conformance.ipp_client import IppClient, IppError, IppSession, numbers
from tests.conformance.nist_grammar import check_response_line

pytestmark = pytest.mark.timeout(60)
ROBOT = default_robot()
FAR = np.array([0.0, 0.0, 500.0])
"""500 mm above home: 2 s of travel at 250 mm/s, clear of every sphere (they sit metres away)."""


@pytest.fixture(scope="module")
def rig() -> SimulatedRig:
    return SimulatedRig(ROBOT, RigConfig(seed=7, errors=load_errors("table2"), cmm_noise_mm=0.0))


@contextmanager
def served(rig: SimulatedRig, **config: object) -> Iterator[tuple[CmmServerHandle, IppClient]]:
    server = start_cmm_server(ROBOT, rig, CmmServerConfig(**{"time_scale": 0.0, "pty": False, "tcp_port": 0,
                                                             **config}))
    client = IppClient.tcp(server.tcp_port)
    try:
        yield server, client
    finally:
        client.close()
        server.close()


def test_lines_and_tags(rig: SimulatedRig) -> None:
    with served(rig) as (_, client):
        ipp = IppSession(client)
        ipp.start(home=False)
        client.send_raw(b"00002 Get(X(\x01))\r\n")  # 6.1.1: 0007 Illegal character, with the line's tag
        assert client.read_transaction("00002").errors == [7]
        ipp.clear()
        client.send_raw(b"00003 IsHomed()\n")  # CR and LF always as a pair
        assert client.read_transaction("00003").errors == [7]
        ipp.clear()
        for line in ("A0004 IsHomed()", "00000 IsHomed()", "E0000 AbortE()", "E0005 IsHomed()", "00006 AbortE()"):
            t = client.exchange(line)  # 6.2.1: illegal tags, and tags of the wrong kind, answered with E0000
            assert (t.lines, t.event_errors) == ([], [1]), line
            ipp.clear()
        assert client.exchange("000070IsHomed()").errors == [2]  # 6.2.2: a space at position 6
        ipp.clear()
        assert client.exchange("00008 Frobnicate()").errors == [507]  # no method of the specification
        ipp.clear()
        unsupported = client.exchange("00009 ScanOnCircleHint(1, 2)")
        assert unsupported.markers == "&!%" and unsupported.errors == [501]
        ipp.clear()
        client.send("00010 GetErrorInfo(" + "1" * 65540 + ")")  # 6.2: longer than 65536 characters
        assert client.read_transaction("00010").errors == [8]
        ipp.clear()
        [text] = ipp.call("GetErrorInfo(1006)").data  # 6.3.1.6: the data is a String
        assert text == '"Surface not found"'
        assert ipp.call("GetDMEVersion()").data == ['DMEVersion("1.4.3")']
        assert ipp.call("GetMachineClass()").data == ["GetMachineClass(CartCMM)"]


def test_sessions(rig: SimulatedRig) -> None:
    with served(rig) as (_, client):
        ipp = IppSession(client)
        assert ipp.call("IsHomed()", check=False).errors == [507]  # 6.3.1: only StartSession and EndSession
        assert ipp.call("EndSession()").markers == "&%"  # without a session it does nothing
        ipp.start()
        ipp.call('SetTool("RefTool")')
        ipp.call("OnPtMeasReport(IJK(), X())")
        again = ipp.call("StartSession()", check=False)
        assert again.errors == [8]  # a second StartSession: 0008 Protocol error
        assert ipp.call("IsHomed()", check=False).errors == [511, 514]  # 0008 has severity 3
        ipp.call("EndSession()")  # "EndSession() followed by a StartSession will start a new session in any case"
        ipp.call("StartSession()")  # ... and implicitly clears the errors (6.3.1.1)
        assert ipp.call("IsHomed()").data == ["IsHomed(1)"]
        assert ipp.call("GetProp(Tool.Name())").data == ['Tool.Name("RefTool")']  # the tool survives sessions
        assert ipp.call("GetCoordSystem()").data == ["CoordSystem(MachineCsy)"]
        assert ipp.call("SetCoordSystem(PartCsy)", check=False).errors == [506]  # MachineCsy only
        ipp.clear()
        centre = rig.to_cmm(ROBOT.base_spheres)[0]
        ipp.goto(centre + 50.0 * np.array([0.0, 0.0, 1.0]))
        report = ipp.ptmeas(centre + ROBOT.sphere_radius_mm * np.array([0.0, 0.0, 1.0]), (0, 0, 1))
        assert len(report) == 3  # the default OnPtMeasReport(X(), Y(), Z()) is back (6.3.1.1)


def test_the_error_state_and_the_pending_transactions(rig: SimulatedRig) -> None:
    with served(rig, time_scale=0.05, home_time_s=0.0) as (_, client):
        ipp = IppSession(client)
        ipp.start()
        ipp.goto(FAR)
        # a PtMeas with nothing to touch (1006, severity 2) and two commands sent behind it, still pending
        client.send_raw(b"00100 PtMeas(X(0), Y(0), Z(400), IJK(0, 0, 1))\r\n"
                        b"00101 Get(X())\r\nE0102 GetErrStatusE()\r\n")
        miss = client.read_transaction("00100")
        pending = client.read_transaction("00101")
        assert miss.markers == "&!%" and miss.errors == [1006]
        assert [line for line in miss.others if line[0] == "E"] == ["E0102 &", "E0102 # ErrStatus(0)", "E0102 %"]
        # ... answered at once, while the PtMeas moved: before its "%" and the "&" of 00101 came with the line
        assert "00101 &" in miss.others and pending.markers == "!%"  # acknowledged, pending ...
        assert pending.errors == [6]  # ... and aborted by the error of severity 2 (6.2.5)
        refused = ipp.call("Get(X())", check=False)
        assert refused.errors == [511, 514]  # as 6.3.1.7 shows, until ClearAllErrors
        assert all(check_response_line(line) == [] for line in refused.lines)
        assert client.exchange("E0104 GetErrStatusE()").data == ["ErrStatus(1)"]
        xtd = ipp.call("GetXtdErrStatus()", check=False)  # status lines and the error the session is in
        assert xtd.data == ["IsHomed(1)", "IsUserEnabled(0)"] and xtd.errors == [1006]
        ipp.clear()
        assert client.exchange("E0105 GetErrStatusE()").data == ["ErrStatus(0)"]
        # after 1006 the ball is back at the approach position: nominal + (Approach 10 + r 1.5) IJK
        assert numbers(ipp.call("Get(X(), Y(), Z())").data[0]) == pytest.approx([0.0, 0.0, 411.5], abs=1e-6)


def test_abort_during_a_running_motion(rig: SimulatedRig) -> None:
    """6.3.1.5: the motion stops, "Transaction aborted" for the executing and the pending commands, AbortE's % after
    them, then only ClearAllErrors (else 0511, 0514)."""
    with served(rig, time_scale=1.0, home_time_s=0.0) as (server, client):
        ipp = IppSession(client)
        ipp.start()
        begun = time.monotonic()
        client.send_raw(b"00100 GoTo(X(0), Y(0), Z(500))\r\n00101 GoTo(Y(300))\r\n")
        assert client.read_line(1.0) == "00100 &" and client.read_line(1.0) == "00101 &"
        time.sleep(0.3)
        assert client.exchange("E0102 GetErrStatusE()").data == ["ErrStatus(0)"]  # the fast queue, while moving
        client.send("E0103 AbortE()")
        lines = [client.read_line(2.0) for _ in range(6)]
        assert lines == ["E0103 &",
                         '00100 ! Error(2, 0006, "GoTo", "Transaction aborted (Use ClearAllErrors To Continue)")',
                         "00100 %",
                         '00101 ! Error(2, 0006, "GoTo", "Transaction aborted (Use ClearAllErrors To Continue)")',
                         "00101 %", "E0103 %"]
        assert time.monotonic() - begun < 1.5  # not the 2 s the move would take
        stopped_z = server.machine.position_mm[2]
        assert 50.0 < stopped_z < 450.0  # stopped on the way
        assert server.machine_time_s == pytest.approx(stopped_z / 250.0, abs=0.03)
        assert ipp.call("Get(X())", check=False).errors == [511, 514]
        assert client.exchange("E0104 GetErrStatusE()").errors == [511, 514]  # only ClearAllErrors
        ipp.clear()
        assert numbers(ipp.call("Get(Z())").data[0]) == [pytest.approx(stopped_z, abs=1e-6)]
        assert server.machine.position_mm[2] == pytest.approx(stopped_z)  # nothing moved after the abort


@pytest.mark.parametrize("time_scale", [0.02, 0.0005])
def test_a_motion_lasts_its_scaled_machine_time(rig: SimulatedRig, time_scale: float) -> None:
    """A GoTo of 500 mm at 250 mm/s is 2 s of machine time: it answers % no sooner than time_scale times that (a
    sample due less than MIN_WAIT_S ahead is taken at once, the motion's last one waited for), ends where it was
    sent and counts its machine time once."""
    with served(rig, time_scale=time_scale, home_time_s=0.0) as (server, client):
        ipp = IppSession(client)
        ipp.start()
        before_s = server.machine_time_s
        begun = time.monotonic()
        ipp.call("GoTo(X(0), Y(0), Z(500))")
        assert time.monotonic() - begun >= 2.0 * time_scale
        assert server.machine.position_mm == pytest.approx([0.0, 0.0, 500.0])
        assert server.machine_time_s - before_s == pytest.approx(2.0, rel=1e-9)


def test_move_reports_while_moving_and_stopping_the_daemon(rig: SimulatedRig) -> None:
    with served(rig) as (_, client):
        ipp = IppSession(client)
        ipp.start()
        assert client.exchange("E0050 OnMoveReportE(Time(0.05))").errors == [510]  # 6.3.2.7: Time >= 0.1
        ipp.clear()
        assert client.exchange("E0051 OnMoveReportE(Dis(20), X(), Z())").markers == "&%"
        assert client.exchange("E0052 OnMoveReportE(Dis(5))").errors == [515]  # one daemon at a time
        ipp.clear()
        moved = ipp.call("GoTo(Z(200))")  # 0.8 s of machine time
        reports = [numbers(line[8:]) for line in moved.others if line.startswith("E0051 #")]
        assert 4 <= len(reports) <= 9  # at most 10 per second, every 20 mm
        zs = [z for _, z in reports]
        assert all(b - a >= 20.0 - 1e-6 for a, b in zip([0.0, *zs], zs, strict=False))
        assert all(x == 0.0 for x, _ in reports) and zs == sorted(zs)
        ipp.call("StopDaemon(E0051)")
        assert not [line for line in ipp.call("GoTo(Z(0))").others if line.startswith("E0051")]
        warning = ipp.call("StopAllDaemons()", check=False)
        assert warning.errors == [512] and ipp.call("IsHomed()").data == ["IsHomed(1)"]  # severity 1: no state
        assert ipp.call("StopDaemon(E0051)", check=False).errors == [513]


def test_emergency_stop_on_both_links(rig: SimulatedRig) -> None:
    with served(rig, time_scale=1.0, home_time_s=0.0, pty=True) as (server, tcp):
        pty = IppClient.pty(server.path)
        try:
            watcher = IppSession(pty)
            watcher.start(home=False)
            ipp = IppSession(tcp)
            ipp.start()
            tcp.send("00100 GoTo(Z(500))")
            assert tcp.read_line(1.0) == "00100 &"
            time.sleep(0.2)
            server.emergency_stop()
            answer = tcp.read_transaction("00100", 2.0)
            stop = '! Error(3, 0500, "HealthCheck", "Emergency stop")'
            # 6.2.4: unsolicited, with E0000; the event and the aborted motion's error go out from different threads
            # of the server, so the event may follow the transaction's % on a busy machine
            events = answer.others or [tcp.read_line(1.0)]
            assert events == [f"E0000 {stop}"]
            assert answer.errors == [500] and answer.markers == "!%"  # the motion stopped (its & read above)
            assert pty.read_line(1.0) == f"E0000 {stop}"  # every link's session hears it
            assert server.machine.position_mm[2] < 200.0
            ipp.clear()
            assert ipp.call("GoTo(Z(0))", check=False).errors == [500]  # refused while pressed
            server.release_emergency_stop()
            assert ipp.call("GoTo(Z(0))", check=False).errors == [511, 514]  # released, not yet cleared
            ipp.clear()
            ipp.call("GoTo(Z(10))")
            watcher.clear()
            assert numbers(watcher.call("Get(Z())").data[0]) == [pytest.approx(10.0)]  # one machine for both
        finally:
            pty.close()


def test_faults_still_work_on_the_new_protocol(rig: SimulatedRig) -> None:
    with served(rig) as (server, client):
        ipp = IppSession(client)
        ipp.start()
        server.faults.inject("silence", command="IsHomed")
        client.send("00100 IsHomed()")
        with pytest.raises(TimeoutError):
            client.read_line(0.3)  # nothing at all, not even the acknowledgement
        server.faults.inject("garbage", command="IsHomed")
        client.send("00101 IsHomed()")
        lines = client.drain(0.2)
        assert lines[0] == "00101 &" and lines[1] == "00101 # IsHomed(1)" and lines[-1] == "00101 %"
        assert len(lines) == 3 + server.config.garbage_lines
        server.faults.inject("partial", command="IsHomed")
        client.send("00102 IsHomed()")
        time.sleep(0.2)
        client.send("00103 IsHomed()")
        assert client.read_line(1.0) == "00102 &"
        assert client.read_line(1.0) == "00102 # Is00103 &"  # the data line cut after 10 bytes, never finished
        assert client.read_transaction("00103").markers == "#%"
        centre = rig.to_cmm(ROBOT.base_spheres)[0]
        up = np.array([0.0, 0.0, 1.0])
        ipp.client.drain(0.2)
        ipp.goto(centre + 40.0 * up)
        server.faults.inject("miss")
        with pytest.raises(IppError) as missed:
            ipp.ptmeas(centre + ROBOT.sphere_radius_mm * up, up)
        assert missed.value.codes == [1006]
        ipp.clear()
        server.faults.inject("outlier")
        outlier = ipp.ptmeas(centre + ROBOT.sphere_radius_mm * up, up)
        normal = ipp.ptmeas(centre + ROBOT.sphere_radius_mm * up, up)
        assert outlier[2] - normal[2] == pytest.approx(server.config.outlier_mm, abs=0.02)


def _spaces_one_by_one(text: str) -> int | None:
    """6.1.4.2's space rule checked space by space (the column of the first space it forbids, or None): spaces
    outside a String only before or after a comma or a '(', or before a ')'; the method starts at column 7."""
    inside = False
    for i in range(6, len(text)):
        if text[i] == '"':
            inside = not inside
        if text[i] != " " or inside:
            continue
        j = i
        while j < len(text) and text[j] == " ":
            j += 1
        before = text[i - 1] if i > 6 else ""
        if not (before in ("(", ",") or text[j:j + 1] in ("(", ")", ",")):
            return i + 1
    return None


def test_the_space_rule_on_random_lines_is_the_one_space_by_space() -> None:
    """The server checks runs of spaces at once; on random lines of names, parentheses, commas, points, quotes and
    spaces it forbids the same first space as the rule read space by space."""
    from sim_devices.cmm.wire import LineError, _check_spaces

    rng = np.random.default_rng(5)
    for _ in range(20000):
        text = "00001 " + "".join(rng.choice(list('X(),1. "'), size=int(rng.integers(0, 13))))
        try:
            _check_spaces(text, "00001")
            column = None
        except LineError as err:
            column = int(str(err).split("column ")[1].split()[0])
        assert column == _spaces_one_by_one(text), text
