"""`hilcal run --sim --instrument tracker` with the simulated tracker set up again during the run (issue 35's live run):
its `[tracker] move_every_poses = 20` moves it 40 mm and turns it 0.5 deg after every 20 poses it measured.

The moved run measures the default plan (its claim of 1.5x needs the 24 verify poses, tests/cli/conftest.py): a move
every 20 of its 83 poses sets the tracker up again once in the measure phase, once in the verification before the
upload and twice in the one after it (5 stations). The run stopped by a move too far measures the calibration plan
(8 verify poses): its claims are the stop and the resume.

Checked against the simulator's own log of its moves, the plan file and the run's own predictions: the run completes
and verifies what its diagnosis predicted (within 1.5x), its diagnosis names no session shift (none was planted); the
journal counts the stations where the simulator moved the tracker by the moves the simulator logged, and the report
names the poses after which it moved as the plan's rows place them; a move beyond the searches (400 mm) stops the
run saying the tracker was moved and how to go on, and the resume with the tracker set up at a new place 30 mm off
(the simulated station then publishes that place's approximate alignment, as an operator gives it in the station
file) completes the run, the station count continuing; free station frames fitted to its recording find nothing to
correct (why the run writes no station column); at an attended station the operator sets the tracker up again when
asked and the pose is measured again.
"""

from __future__ import annotations

import json
import re
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from hilcal.calibration import calibrate
from hilcal.recording import read_recording
from hilcal.robot import default_robot
from procedures import messages as m
from procedures.engine import Engine
from procedures.journal import Journal
from procedures.station import open_devices, station_from_channels
from sim_devices.sim_config import SimConfig, SimTrackerConfig
from sim_devices.simulator import SimHandle, start_sim
from tests.cli.run.test_run_tracker import _hilcal, _rows
from tests.cli.sim_speed import INSTANT_SIM, plan_rows

pytestmark = pytest.mark.timeout(420)

MOVE_EVERY = 20
"""The moved run's poses between the simulator's moves."""
TOO_FAR_AFTER = 20
"""The poses the too-far run measures before the simulator moves the tracker beyond the searches (and the resumed
simulator's poses between its moves)."""
MOVED = INSTANT_SIM.replace("[tracker]\n", f"[tracker]\nmove_every_poses = {MOVE_EVERY}\n")
TOO_FAR = INSTANT_SIM.replace("[tracker]\n", f"[tracker]\nmove_every_poses = {TOO_FAR_AFTER}\nmove_mm = 400.0\n")
SET_UP_ELSEWHERE = INSTANT_SIM.replace("[tracker]\n", f"[tracker]\nmove_every_poses = {TOO_FAR_AFTER}\n"
                                       "station = { x_mm = 6030.0, y_mm = -1500.0, z_mm = 1800.0, yaw_deg = 165.0 }\n")
"""The resume's simulator: the tracker set up 30 mm from its default place (x 6000, y -1500, z 1800 mm, yaw 165 deg)."""


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory, instant_plan: Path, calibration_plan: Path
         ) -> dict[str, tuple[int, str, Path]]:
    """The tracker moved 40 mm every 20 poses (the default plan), and moved 400 mm after 20 poses (the calibration
    plan)."""
    tmp = tmp_path_factory.mktemp("moved")
    (tmp / "moved.toml").write_text(MOVED)
    (tmp / "too_far.toml").write_text(TOO_FAR)
    plans = {"moved": instant_plan, "too_far": calibration_plan}
    done = {name: _hilcal(tmp, "run", "--sim", "--yes", "--instrument", "tracker", "--operator", "T",
                          "--sim-config", str(tmp / f"{name}.toml"), "--plan", str(plan), "--out", str(tmp / name))
            for name, plan in plans.items()}
    return {name: (run.returncode, run.stdout + run.stderr, tmp / name) for name, run in done.items()}


def _details(run: Path) -> list[dict]:
    return [json.loads(detail) for _, _, detail in _rows(run)]


def _events(run: Path, kind: str) -> list[dict]:
    db = sqlite3.connect(f"file:{run / 'journal.sqlite'}?mode=ro", uri=True)
    try:
        return [json.loads(d) for (d,) in db.execute("SELECT data_json FROM events WHERE kind = ? ORDER BY id",
                                                     (kind,))]
    finally:
        db.close()


def _simulator_moves(run: Path) -> list[dict]:
    """The simulator's log of its moves (sim.log, structlog's console lines): after how many poses, from where to
    where ([x, y, z mm, roll, pitch, yaw deg] in the base frame)."""
    moves = []
    for line in (run / "sim.log").read_text().splitlines():
        if "tracker_sim.moved" not in line:
            continue
        fields = dict(re.findall(r"(\w+)=(\[[^\]]*\]|\S+)", line))
        moves.append({"after_poses": int(fields["after_poses"]),
                      "before": np.array(json.loads(fields["station_before"])),
                      "after": np.array(json.loads(fields["station_after"]))})
    return moves


def _pose_name(k: int, plan: Path) -> str:
    """The k-th pose (from 1) that a whole run of `plan` measures, named by its phase and its number in the phase: the
    plan's measure rows (with the repeats), then its verify poses before the upload and again after it."""
    n_measure, n_verify = plan_rows(plan)
    for phase, n in (("measure", n_measure), ("verify", n_verify // 2), ("verify after", n_verify // 2)):
        if k <= n:
            return f"{phase} pose {k}"
        k -= n
    raise ValueError(f"a run of {plan} measures fewer than {k} more poses")


def _turn_deg(a: np.ndarray, b: np.ndarray) -> float:
    ra, rb = (Rotation.from_euler("ZYX", p[[5, 4, 3]], degrees=True) for p in (a, b))
    return float(np.degrees((rb * ra.inv()).magnitude()))


@pytest.mark.slow
def test_the_run_with_a_moved_tracker_verifies_what_its_diagnosis_predicts(runs) -> None:
    code, stdout, run = runs["moved"]
    assert code == 0, stdout
    report = json.loads((run / "report.json").read_text())
    assert report["status"] == "complete" and report["uploaded"] is True
    measured = report["verification"]["after"]["rms_position_mm"]
    predicted = report["physics"]["predicted_with_physics"]["rms_position_mm"]
    assert measured <= 1.5 * predicted, (measured, predicted)
    assert report["verification"]["before"]["rms_position_mm"] > 20 * measured
    physics = report["physics"]
    named = [*physics["effects"], *physics["corrected"], *physics["not_corrected"], *physics["explained"]]
    assert named == [] and not any("session" in f for f in physics["findings"]), physics["findings"]
    assert "station" not in (run / "recording.csv").read_text().splitlines()[0].split(",")


@pytest.mark.slow
def test_the_journal_counts_the_stations_where_the_simulator_moved_the_tracker(runs, instant_plan: Path) -> None:
    code, stdout, run = runs["moved"]
    assert code == 0, stdout
    details = _details(run)
    n_rows = sum(plan_rows(instant_plan))
    assert len(details) == n_rows
    moves = _simulator_moves(run)
    rows = [mv["after_poses"] for mv in moves]
    assert rows == list(range(MOVE_EVERY, n_rows, MOVE_EVERY))
    expected_after = [_pose_name(row, instant_plan) for row in rows]
    assert {name.rsplit(" pose ", 1)[0] for name in expected_after} == {"measure", "verify", "verify after"}, \
        "the moves fall in every phase of the run"
    stations = [d["station"] for d in details]
    assert stations == [1 + sum(k >= row for row in rows) for k in range(n_rows)]
    changes = _events(run, "station_change")
    assert [c["station"] for c in changes] == list(range(2, len(moves) + 2))
    for change, mv, row in zip(changes, moves, rows, strict=True):
        assert details[row]["station_change"] == {k: v for k, v in change.items() if k not in ("phase", "index")}
        assert change["moved_mm"] == pytest.approx(np.linalg.norm(mv["after"][:3] - mv["before"][:3]), abs=0.3)
        assert change["turned_deg"] == pytest.approx(_turn_deg(mv["before"], mv["after"]), abs=0.005)
        np.testing.assert_allclose(details[row]["station_pose"][:3], mv["after"][:3], atol=0.3)
        assert details[row]["widened_searches"] > 0 and change["monument_shift_mm"] > 30.0
    report = json.loads((run / "report.json").read_text())
    assert report["stations"]["count"] == len(moves) + 1 and report["stations"]["recording_station_column"] is False
    assert [mv["after_pose"] for mv in report["stations"]["moves"]] == expected_after
    assert f"{len(moves) + 1} stations: set up again after {expected_after[0]}, {expected_after[1]}" in stdout
    assert "Instrument stations" in (run / "report.html").read_text()


@pytest.mark.slow
def test_a_move_beyond_the_searches_stops_the_run_and_the_resume_completes_it(runs, calibration_plan: Path) -> None:
    code, stdout, run = runs["too_far"]
    assert code == 3, stdout
    said = " ".join(stdout.split())  # the terminal wraps the message
    assert "TrackerMoved: the tracker was moved: base monument 1 is not within 100 mm" in said
    assert "Set the tracker up again nearer that place, or give its new approximate alignment in the station file's " \
           "[tracker] alignment" in said
    done_before = _rows(run)
    assert len(done_before) == TOO_FAR_AFTER and len(_events(run, "tracker_moved")) == 1
    resume = said[said.index("hilcal run --resume"):].split()[:6]
    (run.parent / "too_far.toml").write_text(SET_UP_ELSEWHERE)
    resumed = _hilcal(run.parent, *resume[1:], "--yes")
    assert resumed.returncode == 0, resumed.stdout + resumed.stderr
    rows = _rows(run)
    n_rows = sum(plan_rows(calibration_plan))
    assert len(rows) == n_rows and rows[:TOO_FAR_AFTER] == done_before
    # the resumed simulator counts its own poses: the tracker set up elsewhere, then moved every TOO_FAR_AFTER poses
    expected = [1] * TOO_FAR_AFTER + [2 + k // TOO_FAR_AFTER for k in range(n_rows - TOO_FAR_AFTER)]
    assert [d["station"] for d in _details(run)] == expected
    changes = _events(run, "station_change")
    assert [c["station"] for c in changes] == list(range(2, expected[-1] + 1))
    assert changes[0]["moved_mm"] == pytest.approx(30.0, abs=0.3) and changes[0]["turned_deg"] < 0.005
    report = json.loads((run / "report.json").read_text())
    assert report["stations"]["count"] == expected[-1]
    assert report["stations"]["moves"][0]["after_pose"] == _pose_name(TOO_FAR_AFTER, calibration_plan)


@pytest.mark.slow
def test_free_station_frames_in_the_fit_would_find_nothing_to_correct(runs, instant_plan: Path, tmp_path: Path
                                                                      ) -> None:
    """Why the run writes no station column: its rows are registered on the monuments, so a free frame per station
    (hilcal/stations.py) fitted with the geometry comes out at the registrations' noise, and only widens the
    parameters' standard errors."""
    code, stdout, run = runs["moved"]
    assert code == 0, stdout
    lines = (run / "recording.csv").read_text().splitlines()
    station = dict(enumerate((d["station"] - 1 for d in _details(run)), start=1))  # by the journal's seq
    seq = lines[0].split(",").index("seq")
    (tmp_path / "stations.csv").write_text("\n".join([lines[0] + ",station", *(
        f"{line},{station[int(line.split(',')[seq])]}" for line in lines[1:])]))
    robot = default_robot()
    registered = calibrate(read_recording(run / "recording.csv", robot), robot).identification
    framed = calibrate(read_recording(tmp_path / "stations.csv", robot), robot).identification
    n_measure, _ = plan_rows(instant_plan)
    measure_moves = sum(mv["after_poses"] < n_measure for mv in _simulator_moves(run))
    assert measure_moves >= 1, "the measure rows were taken at more than one station"
    # a frame for each of the measure rows' stations but the first (the column counts stations from 0)
    assert framed.station_frames is not None and set(framed.station_frames) == set(range(1, measure_moves + 1))
    for frame in framed.station_frames.values():
        assert np.linalg.norm(frame[:3]) < 0.05 and np.degrees(np.linalg.norm(frame[3:])) < 0.005
    assert np.all(framed.std_errors >= registered.std_errors * (1 - 1e-9))


@pytest.fixture
def sim() -> Iterator[SimHandle]:
    config = SimConfig(instrument="tracker", tracker=SimTrackerConfig(time_scale=0.0, move_every_poses=1,
                                                                     move_mm=400.0))
    with start_sim(config) as handle:
        yield handle


def test_an_operator_sets_the_moved_tracker_up_again_when_asked(sim: SimHandle, tmp_path: Path) -> None:
    """Attended: the tracker moved 400 mm after the first pose, the run asks; the operator carries it to 25 mm from
    its first place and says yes; the pose is measured again and is the second station's first."""
    asked: list[str] = []
    first_place = sim.tracker_server.station

    def operator(text: str) -> bool:
        asked.append(text)
        if text.startswith("the tracker was moved"):
            sim.tracker_server.set_station(first_place + np.array([0.0, 25.0, 0.0, 0.0, 0.0, 0.0]))
        return True

    def poses():
        yield m.PrepareCmm()
        yield m.Enable()
        first = yield m.Measure("measure", 0, m.as_tuple(sim.robot.home))
        second = yield m.Measure("measure", 1, m.as_tuple(sim.robot.home))
        yield m.Disable()
        return first, second

    with open_devices(station_from_channels(sim.channels())) as devices, Journal(tmp_path / "j.sqlite") as journal:
        first, second = Engine(devices, journal, confirm=operator).run(poses())
        prompts = [e["data"] for e in journal.events("prompt")]
    assert len(asked) == 1 and asked[0].endswith("Set the tracker up again near that place now (its monuments are "
                                                 "searched for again): measure the pose again?")
    assert prompts == [{"key": "tracker_moved", "text": asked[0], "answer": True, "unattended": False}]
    assert first["detail"]["station"] == 1 and second["detail"]["station"] == 2
    assert second["detail"]["station_change"]["moved_mm"] == pytest.approx(25.0, abs=0.3)
    truth = sim.rig.true_pose()
    assert np.max(np.abs(np.asarray(second["meas"])[:3] - truth[:3])) < 0.2
