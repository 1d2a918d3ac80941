"""Calibration records in a real SQLite file, and the upload/rollback helpers against the simulated controller
over Modbus TCP on 127.0.0.1 (no mocks). Hashes are recomputed here with struct + hashlib."""

from __future__ import annotations

import hashlib
import json
import sqlite3
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from drivers.controller.modbus import ControllerParams, ModbusTransportError, NotDisabled, UploadRefused
from hilcal.protocols.controller_states import Command
from hilcal.robot import Robot
from procedures.records import (
    ParameterFileError,
    Records,
    RecordsError,
    UploadDeclined,
    format_history,
    rollback_controller,
    upload_parameter_file,
)
from sim_devices.controller.modbus_server import ModbusTcpServer
from sim_devices.controller.state_machine import ControllerSimConfig, SimulatedController
from sim_devices.rig.config import GeometryErrors, RigConfig
from sim_devices.rig.rig import SimulatedRig

pytestmark = pytest.mark.timeout(60)


def f32(values: np.ndarray) -> np.ndarray:
    return np.asarray(values, dtype=np.float32).astype(float)


def sha_of(values: np.ndarray) -> str:
    """SHA-256 of the 42 float32 big-endian registers, as docs/protocols.md defines the set's hash."""
    return hashlib.sha256(struct.pack(">42f", *values)).hexdigest()


def nominal(robot: Robot) -> np.ndarray:
    return np.concatenate([robot.a.ravel(), robot.b.ravel(), robot.l0])


def as_file_dict(values: np.ndarray) -> dict:
    return {"a_mm": values[:18].reshape(6, 3).tolist(), "b_mm": values[18:36].reshape(6, 3).tolist(),
            "l0_mm": values[36:].tolist()}


@pytest.fixture
def db(tmp_path: Path) -> Iterator[Records]:
    with Records(tmp_path / "records" / "records.sqlite") as records:
        yield records


@dataclass
class Sim:
    controller: SimulatedController
    server: ModbusTcpServer
    params: ControllerParams


@pytest.fixture
def sim(robot: Robot) -> Iterator[Sim]:
    rig = SimulatedRig(robot, RigConfig(seed=3, errors=GeometryErrors.zero()))
    controller = SimulatedController(robot, rig, ControllerSimConfig())
    server = ModbusTcpServer(controller).start()
    params = ControllerParams("127.0.0.1", server.port, device_id=1, timeout_s=1.0)
    yield Sim(controller, server, params)
    params.close()
    server.close()


# ------------------------------------------------------------------ the database


def test_schema_wal_and_foreign_keys(tmp_path: Path) -> None:
    path = tmp_path / "r.sqlite"
    with Records(path) as records:
        with pytest.raises(RecordsError, match="no-such-run"):
            records.record_upload({"outcome": "committed", "endpoint": "tcp://x:1"}, "ann", run_id="no-such-run")
    raw = sqlite3.connect(path)
    try:
        assert raw.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        columns = {t: [r[1] for r in raw.execute(f"PRAGMA table_info({t})")] for t in ("runs", "parameter_sets",
                                                                                        "uploads")}
        assert columns["runs"] == ["run_id", "started_at", "finished_at", "status", "robot_name", "plan_sha256",
                                   "operator", "out_dir", "estimator", "verify_before_json", "verify_after_json",
                                   "machine", "station", "machine_serial", "verdict", "certificate_number",
                                   "certificate_path"]
        assert columns["parameter_sets"] == ["id", "sha256", "created_at", "source", "json"]
        assert columns["uploads"] == ["id", "run_id", "time", "operator", "endpoint", "params_sha256", "outcome",
                                      "record_json", "upload_id", "machine", "station"]
        with pytest.raises(sqlite3.IntegrityError):
            raw.execute("INSERT INTO parameter_sets (sha256, created_at, source, json) "
                        "VALUES ('x', 't', 'guess', '{}')")
        raw.rollback()
        raw.execute("PRAGMA foreign_keys=ON")
        with pytest.raises(sqlite3.IntegrityError):
            raw.execute("INSERT INTO uploads (run_id, time, outcome, record_json, upload_id) "
                        "VALUES ('no-such-run', 't', 'committed', '{}', 'u1')")
    finally:
        raw.close()
    with Records(path) as again:  # reopening an existing file keeps it usable
        assert again.history() == []


def test_run_round_trip_and_update(db: Records) -> None:
    before = {"max_position_mm": 6.9595, "rms_position_mm": 6.1455, "max_orientation_deg": 0.6977,
              "rms_orientation_deg": 0.5971}
    db.record_run("r1", started_at="2025-03-01T08:00:00+00:00", status="running", robot_name="rig-A",
                  plan_sha256="p" * 64, operator="ann", out_dir=Path("/data/r1"), estimator="linf",
                  verify_before=before)
    db.update_run("r1", status="complete", finished_at="2025-03-01T09:00:00+00:00",
                  verify_after={"max_position_mm": 0.9408})
    run = db.run("r1")
    assert run is not None
    assert (run["status"], run["robot_name"], run["operator"], run["out_dir"], run["estimator"]) == (
        "complete", "rig-A", "ann", "/data/r1", "linf")
    assert run["verify_before"] == before and run["verify_after"] == {"max_position_mm": 0.9408}
    assert run["finished_at"] == "2025-03-01T09:00:00+00:00" and run["uploads"] == []
    with pytest.raises(RecordsError, match="unknown run fields"):
        db.update_run("r1", colour="red")
    with pytest.raises(RecordsError, match="no run"):
        db.update_run("r2", status="complete")
    with pytest.raises(RecordsError, match="already recorded"):
        db.record_run("r1", started_at="2025-03-02T08:00:00+00:00", status="running")
    db.record_run("r1", started_at="2025-03-01T08:00:00+00:00", status="running")  # a retried write: a no-op
    assert db.run("r1")["status"] == "complete"


def test_parameter_sets_are_keyed_by_the_controller_hash(db: Records, robot: Robot) -> None:
    values = nominal(robot) + 0.1
    sha = db.add_parameter_set(as_file_dict(values), "identified")
    assert sha == sha_of(values)
    assert db.add_parameter_set(as_file_dict(values), "file") == sha  # stored once
    stored = db.parameter_set(sha)
    assert stored is not None and stored["source"] == "identified" and stored["params"] == as_file_dict(values)
    other = db.add_parameter_set({"leg1_dl0_mm": 0.5}, "identified")
    assert other == hashlib.sha256(b'{"leg1_dl0_mm":0.5}').hexdigest()
    with pytest.raises(RecordsError, match="source"):
        db.add_parameter_set({"x": 1.0}, "guess")  # type: ignore[arg-type]


def test_history_newest_first_with_uploads_and_limit(db: Records) -> None:
    for run_id, start in (("r-mid", "2025-03-02T08:00:00+00:00"), ("r-old", "2025-03-01T08:00:00+00:00"),
                          ("r-new", "2025-03-03T08:00:00+00:00")):
        db.record_run(run_id, started_at=start, status="complete", operator="ann")
    db.record_upload({"operation": "upload", "outcome": "committed", "endpoint": "tcp://a:502",
                      "started_at": "2025-03-02T08:30:00+00:00", "finished_at": "2025-03-02T08:31:00+00:00",
                      "params_sha256": "1" * 64}, "ann", run_id="r-mid")
    db.record_upload({"operation": "upload", "outcome": "refused", "endpoint": "tcp://a:502",
                      "started_at": "2025-03-02T08:20:00+00:00", "finished_at": "2025-03-02T08:20:01+00:00"},
                     "ann", run_id="r-mid")
    db.record_upload({"operation": "rollback", "outcome": "rolled_back", "endpoint": "tcp://a:502",
                      "started_at": "2025-03-02T12:00:00+00:00", "finished_at": "2025-03-02T12:00:01+00:00"}, "bob")
    rows = db.history()
    assert [r.get("run_id") if r["kind"] == "run" else r["record"]["operation"] for r in rows] == [
        "r-new", "rollback", "r-mid", "r-old"]
    mid = rows[2]
    assert [u["outcome"] for u in mid["uploads"]] == ["refused", "committed"]  # oldest first within a run
    assert [r["run_id"] for r in db.history(limit=2, include_standalone=False)] == ["r-new", "r-mid"]
    assert len(db.history(limit=1)) == 1
    text = format_history(rows)
    lines = text.splitlines()
    order = [next(i for i, line in enumerate(lines) if key in line) for key in ("r-new", "rollback", "r-mid", "r-old")]
    assert order == sorted(order)
    assert "refused" in text and "committed" in text and "bob" in text
    assert format_history([]) == "no runs or uploads recorded"


def test_last_upload_by_endpoint_and_outcome(db: Records) -> None:
    assert db.last_upload() is None
    for endpoint, outcome, t in (("tcp://a:502", "committed", "2025-03-01T10:00:00+00:00"),
                                 ("tcp://b:502", "failed", "2025-03-01T11:00:00+00:00"),
                                 ("tcp://a:502", "refused", "2025-03-01T12:00:00+00:00")):
        db.record_upload({"outcome": outcome, "endpoint": endpoint, "finished_at": t}, "ann")
    last = db.last_upload()
    assert last is not None and last["outcome"] == "refused"
    last_b = db.last_upload("tcp://b:502")
    assert last_b is not None and last_b["outcome"] == "failed"
    committed = db.last_upload("tcp://a:502", outcome="committed")
    assert committed is not None and committed["time"] == "2025-03-01T10:00:00+00:00"


# ------------------------------------------------------------------ upload and rollback on the simulated controller


def write_file(tmp_path: Path, values: np.ndarray | dict | str, name: str = "params.json") -> Path:
    path = tmp_path / name
    path.write_text(values if isinstance(values, str) else json.dumps(
        values if isinstance(values, dict) else as_file_dict(values)))
    return path


def test_upload_file_shows_diff_commits_and_records(sim: Sim, db: Records, robot: Robot, tmp_path: Path) -> None:
    new = nominal(robot).copy()
    new[0] += 0.25  # leg 1, a_x
    new[36 + 1] -= 0.5  # leg 2, l0
    prompts: list[str] = []
    result = upload_parameter_file(sim.params, write_file(tmp_path, new), db, "ann", save=False, yes=False,
                                   confirm=lambda text: prompts.append(text) or True)
    assert [d["name"] for d in result["diff"]] == ["leg1_a_x_mm", "leg2_l0_mm"]
    assert [d["delta_mm"] for d in result["diff"]] == pytest.approx([0.25, -0.5], abs=1e-4)
    assert len(prompts) == 1 and "leg1_a_x_mm" in prompts[0] and "leg2_l0_mm" in prompts[0]
    assert "leg3_l0_mm" not in prompts[0]
    np.testing.assert_array_equal(sim.controller.live_parameters(), f32(new))
    record = result["record"]
    assert record["outcome"] == "committed" and record["params_sha256"] == sha_of(f32(new))
    assert result["file_sha256"] == sha_of(f32(new))
    last = db.last_upload(sim.params.endpoint)
    assert last is not None and last["outcome"] == "committed" and last["operator"] == "ann"
    assert last["params_sha256"] == sha_of(f32(new)) and last["record"]["live_readback_match"] is True
    assert db.parameter_set(sha_of(f32(new)))["source"] == "file"
    assert db.parameter_set(sha_of(f32(nominal(robot))))["source"] == "controller"


def test_a_file_with_a_compensation_block_uploads_both_and_rollback_restores_both(
        sim: Sim, db: Records, robot: Robot, tmp_path: Path) -> None:
    new = nominal(robot).copy()
    new[36] += 0.1
    block = {"scale_ppm": [-2990.0, 0, 0, 0, 0, 0], "backlash_mm": [0.0] * 6, "compliance_mm_per_kn": [0.006] * 6,
             "compliance_mm_per_kn_m": [0.0] * 6, "thermal_ppm_per_k": [0.0] * 6, "table_start_mm": [0.0] * 6,
             "table_end_mm": [0.0] * 6, "table_mm": [[] for _ in range(6)]}
    prompts: list[str] = []
    result = upload_parameter_file(sim.params, write_file(tmp_path, {**as_file_dict(new), "compensation": block}),
                                   db, "ann", save=False, yes=False, confirm=lambda t: prompts.append(t) or True)
    assert result["compensation_changes"] and "compensation block" in prompts[0]
    assert result["record"]["compensation_readback_match"] is True
    assert sim.controller.live_compensation()["scale_ppm"][0] == pytest.approx(-2990.0)
    rollback_controller(sim.params, db, "ann")
    assert sim.controller.live_compensation()["scale_ppm"][0] == 0.0
    np.testing.assert_array_equal(sim.controller.live_parameters(), f32(nominal(robot)))
    bad = write_file(tmp_path, {**as_file_dict(new), "compensation": {**block, "scale_ppm": [1e6] * 6}}, "bad.json")
    with pytest.raises(ParameterFileError, match="compensation"):
        upload_parameter_file(sim.params, bad, db, "ann", save=False, yes=True, confirm=lambda _: True)
    assert sim.controller.live_compensation()["scale_ppm"][0] == 0.0


def test_upload_with_yes_does_not_ask_and_saves(sim: Sim, db: Records, robot: Robot, tmp_path: Path) -> None:
    new = nominal(robot) + 0.125

    def never(_: str) -> bool:
        raise AssertionError("confirm must not be called with yes=True")

    result = upload_parameter_file(sim.params, write_file(tmp_path, new), db, "ann", save=True, yes=True,
                                   confirm=never)
    assert result["record"]["saved"] is True and len(result["diff"]) == 42
    np.testing.assert_array_equal(sim.controller.saved_parameters(), f32(new))


def test_declined_upload_writes_nothing_and_is_recorded(sim: Sim, db: Records, robot: Robot, tmp_path: Path) -> None:
    new = nominal(robot) + 0.2
    with pytest.raises(UploadDeclined):
        upload_parameter_file(sim.params, write_file(tmp_path, new), db, "ann", save=False, yes=False,
                              confirm=lambda _: False)
    assert sim.server.writes == []
    np.testing.assert_array_equal(sim.controller.live_parameters(), f32(nominal(robot)))
    last = db.last_upload()
    assert last is not None and last["outcome"] == "refused" and "declined" in last["record"]["error"]


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("{not json", "not JSON"),
        ("[1, 2, 3]", "JSON object"),
        ({"a_mm": [[0.0, 0.0, 0.0]] * 6, "b_mm": [[0.0, 0.0, 0.0]] * 6}, "l0_mm"),
        ("bad_l0", "l0_mm"),
        ("extra_key", "colour"),
        ({"a_mm": [[0.0, 0.0]] * 6, "b_mm": [[0.0, 0.0, 0.0]] * 6, "l0_mm": [1.0] * 6}, r"a_mm\[0\]"),
    ],
)
def test_invalid_file_is_refused_clearly_and_recorded(
    sim: Sim, db: Records, robot: Robot, tmp_path: Path, content: object, message: str
) -> None:
    if content == "bad_l0":
        bad = as_file_dict(nominal(robot))
        bad["l0_mm"][2] = 1e9
        content = bad
    elif content == "extra_key":
        content = dict(as_file_dict(nominal(robot)), colour="red")
    with pytest.raises(ParameterFileError, match=message):
        upload_parameter_file(sim.params, write_file(tmp_path, content), db, "ann", save=False, yes=True,
                              confirm=lambda _: True)
    assert sim.server.writes == []
    last = db.last_upload()
    assert last is not None and last["outcome"] == "refused" and "ParameterFileError" in last["record"]["error"]


def test_missing_file_is_refused(sim: Sim, db: Records, tmp_path: Path) -> None:
    with pytest.raises(ParameterFileError, match="cannot read"):
        upload_parameter_file(sim.params, tmp_path / "nope.json", db, "ann", save=False, yes=True,
                              confirm=lambda _: True)


def test_failed_upload_is_recorded_as_failed(sim: Sim, db: Records, robot: Robot, tmp_path: Path) -> None:
    new = nominal(robot) + 0.3
    sim.server.faults.drop_connection_at_write(2)
    with pytest.raises(ModbusTransportError) as info:
        upload_parameter_file(sim.params, write_file(tmp_path, new), db, "ann", save=False, yes=True,
                              confirm=lambda _: True)
    assert info.value.record is not None
    last = db.last_upload(sim.params.endpoint)
    assert last is not None and last["outcome"] == "failed" and last["operator"] == "ann"
    assert last["params_sha256"] == sha_of(f32(new))
    writes = last["record"]["writes"]
    assert len(writes) == 2 and writes[-1]["ok"] is False and writes[-1]["error"]
    np.testing.assert_array_equal(sim.controller.live_parameters(), f32(nominal(robot)))


def test_refused_upload_while_enabled_is_recorded(sim: Sim, db: Records, robot: Robot, tmp_path: Path) -> None:
    sim.controller.command(Command.ENABLE)
    with pytest.raises(NotDisabled):
        upload_parameter_file(sim.params, write_file(tmp_path, nominal(robot) + 0.3), db, "ann", save=False,
                              yes=True, confirm=lambda _: True)
    last = db.last_upload()
    assert last is not None and last["outcome"] == "refused" and "NotDisabled" in last["record"]["error"]
    assert sim.server.writes == []


def test_unchanged_file_is_not_reuploaded(sim: Sim, db: Records, robot: Robot, tmp_path: Path) -> None:
    path = write_file(tmp_path, nominal(robot))
    result = upload_parameter_file(sim.params, path, db, "ann", save=False, yes=True, confirm=lambda _: True)
    assert result == {"record": None, "diff": [], "changed": False, "compensation_changes": False,
                      "file_sha256": sha_of(f32(nominal(robot)))}
    assert sim.server.writes == [] and db.last_upload() is None
    saved = upload_parameter_file(sim.params, path, db, "ann", save=True, yes=True, confirm=lambda _: True)
    assert saved["record"]["operation"] == "save" and saved["record"]["outcome"] == "saved"
    last = db.last_upload()
    assert last is not None and last["outcome"] == "saved"


def test_rollback_restores_and_is_recorded(sim: Sim, db: Records, robot: Robot, tmp_path: Path) -> None:
    with pytest.raises(UploadRefused):  # nothing to roll back to yet
        rollback_controller(sim.params, db, "ann")
    refused = db.last_upload()
    assert refused is not None and refused["outcome"] == "refused" and refused["record"]["operation"] == "rollback"
    new = nominal(robot) + 0.4
    upload_parameter_file(sim.params, write_file(tmp_path, new), db, "ann", save=False, yes=True,
                          confirm=lambda _: True)
    record = rollback_controller(sim.params, db, "bob")
    assert record["outcome"] == "rolled_back" and record["params_sha256"] == sha_of(f32(nominal(robot)))
    np.testing.assert_array_equal(sim.controller.live_parameters(), f32(nominal(robot)))
    history = db.history(include_standalone=True)
    assert [(h["record"]["operation"], h["outcome"]) for h in history] == [
        ("rollback", "rolled_back"), ("upload", "committed"), ("rollback", "refused")]
    assert "bob" in format_history(history)
