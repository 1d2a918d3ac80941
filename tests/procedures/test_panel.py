"""The operator panel without a browser: live state, prompt arbitration, security rules, history, the HTTP stream."""

from __future__ import annotations

import asyncio
import json
import signal
import socket
import subprocess
import sys
import threading
import time

import httpx2 as httpx
import numpy as np
import pytest
from starlette.testclient import TestClient

from procedures import messages as m
from procedures.panel.app import PanelContext, build_app
from procedures.panel.control import OperatorControl, PanelRequestError
from procedures.panel.live import LiveState
from procedures.panel.run_view import RunView, measurement_item
from procedures.panel.server import PanelServer, PanelStartError
from procedures.records import Records


def _apply(snapshot: dict, event: dict) -> None:
    """The page's reducer, written again here: set or append one section."""
    if event["op"] == "set":
        snapshot["sections"][event["section"]] = event["value"]
    else:
        snapshot["sections"][event["section"]].append(event["value"])
    snapshot["seq"] = event["seq"]


def test_live_state_a_late_subscriber_sees_what_an_early_one_built():
    live = LiveState()

    async def scenario() -> tuple[dict, dict]:
        first_snap, first_q = live.subscribe()
        writer = threading.Thread(target=lambda: [live.append("measurements", {"i": i}) or
                                                  live.update("progress", done=i + 1) for i in range(50)])
        writer.start()
        await asyncio.to_thread(writer.join)
        early = json.loads(first_snap)
        for _ in range(100):
            _apply(early, json.loads(await asyncio.wait_for(first_q.get(), 2)))
        late_snap, _ = live.subscribe()
        return early, json.loads(late_snap)

    early, late = asyncio.run(scenario())
    assert early["seq"] == late["seq"] == 100
    assert early["sections"] == late["sections"]
    assert [x["i"] for x in late["sections"]["measurements"]] == list(range(50))
    assert late["sections"]["progress"] == {"done": 50}


def test_live_state_close_ends_every_stream():
    live = LiveState()

    async def scenario() -> object:
        _, queue = live.subscribe()
        threading.Thread(target=live.close).start()
        return await asyncio.wait_for(queue.get(), 2)

    assert asyncio.run(scenario()) is None


def test_measurement_item_is_the_measured_vs_commanded_error():
    cmd = np.array([10.0, 20.0, 2900.0, 1.0, -2.0, 3.0])
    meas = cmd + np.array([0.3, 0.4, 0.0, 0.0, 0.0, 0.0])
    item = measurement_item({"phase": "verify", "index": 4, "seq": 9, "time_s": 1.0, "cmd": cmd, "meas": meas,
                             "detail": {"sphere_fit_rms_mm": 0.002}})
    assert item["position_error_mm"] == pytest.approx(0.5)
    assert item["orientation_error_deg"] == pytest.approx(0.0, abs=1e-9)
    turned = measurement_item({"phase": "verify", "index": 4, "seq": 9, "time_s": 1.0, "cmd": cmd * [1, 1, 1, 0, 0, 0],
                               "meas": cmd * [1, 1, 1, 0, 0, 0] + [0, 0, 0, 0.25, 0, 0], "detail": {}})
    assert turned["orientation_error_deg"] == pytest.approx(0.25, rel=1e-6)


def _row(phase: str, index: int, seq: int) -> dict:
    pose = np.array([0.0, 0.0, 3000.0, 0.0, 0.0, 0.0])
    return {"phase": phase, "index": index, "seq": seq, "time_s": float(seq), "cmd": pose, "meas": pose, "detail": {}}


def test_run_view_counts_each_pose_once_across_a_resume():
    live = LiveState()
    view = RunView(live)
    view.total = 5
    view.on_engine_event("done", {"message": m.Recall(("measure",)), "result": [_row("measure", 0, 1),
                                                                               _row("measure", 1, 2)]})
    view.on_engine_event("message", {"message": m.MoveLegs((0.0,) * 6, "measure 3 approach")})
    assert live.get("progress")["pose"] == 3 and live.get("progress")["phase"] == "measure"
    view.on_engine_event("done", {"message": m.Measure("measure", 2, (0.0,) * 6), "result": _row("measure", 2, 3)})
    view.on_engine_event("done", {"message": m.Recall(("measure",)), "result": [_row("measure", i, i + 1)
                                                                               for i in range(3)]})
    assert len(live.get("measurements")) == 3
    progress = live.get("progress")
    assert (progress["done"], progress["total"]) == (3, 5)
    assert progress["remaining_s"] is not None and progress["remaining_s"] >= 0


def _control(**kw) -> tuple[OperatorControl, list[dict]]:
    journal: list[dict] = []
    control = OperatorControl(LiveState(), say=lambda text: None, **kw)
    control.journal_event = lambda kind, **data: journal.append({"kind": kind, **data})
    return control, journal


def _ask_in_thread(control: OperatorControl, text: str) -> tuple[threading.Thread, dict]:
    out: dict = {}
    thread = threading.Thread(target=lambda: out.setdefault("answer", control.confirm(text)))
    thread.start()
    deadline = time.monotonic() + 5
    while control.live.get("prompt") is None or not control.live.get("prompt")["open"]:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    return thread, out


def test_first_answer_wins_and_is_journaled_with_operator_and_source():
    control, journal = _control(operator="J. Smith")
    control.on_engine_event("message", {"message": m.Prompt("area", "Clear the area?")})
    thread, out = _ask_in_thread(control, "Clear the area?")
    qid = control.live.get("prompt")["id"]
    control.terminal_line("y")
    thread.join(5)
    with pytest.raises(PanelRequestError, match="no longer open"):
        control.answer(qid, False, client="127.0.0.1:5000")
    assert out["answer"] is True
    (entry,) = journal
    assert entry["kind"] == "operator_answer" and entry["key"] == "area"
    assert (entry["answer"], entry["operator"], entry["via"]) == (True, "J. Smith", "terminal")
    assert entry["answered_at"] >= entry["asked_at"]


def test_page_answer_wins_over_a_later_terminal_line():
    control, journal = _control(operator="A. Operator")
    control.on_engine_event("message", {"message": m.Prompt("spheres", "Spheres mounted?")})
    thread, out = _ask_in_thread(control, "Spheres mounted?")
    control.answer(control.live.get("prompt")["id"], False, client="127.0.0.1:5001")
    thread.join(5)
    control.terminal_line("y")
    assert out["answer"] is False
    assert [(e["via"], e["answer"], e["client"]) for e in journal] == [("page", False, "127.0.0.1:5001")]


def test_upload_approval_needs_the_sha256_of_the_set_shown():
    control, journal = _control(operator="J. Smith")
    detail = {"new_sha256": "ab" * 32, "diff": [{"name": "leg1_l0_mm", "live_mm": 1.0, "new_mm": 1.5,
                                                  "delta_mm": 0.5}]}
    control.on_engine_event("message", {"message": m.Prompt("upload", "Upload?", detail)})
    thread, out = _ask_in_thread(control, "Upload?")
    prompt = control.live.get("prompt")
    assert prompt["kind"] == "upload" and prompt["detail"]["diff"][0]["delta_mm"] == 0.5
    for wrong in (None, "cd" * 32):
        with pytest.raises(PanelRequestError, match="explicit confirmation") as err:
            control.answer(prompt["id"], True, confirm_sha256=wrong)
        assert err.value.status == 400
    assert thread.is_alive() and journal == []
    control.answer(prompt["id"], True, confirm_sha256="ab" * 32)
    thread.join(5)
    assert out["answer"] is True and journal[0]["via"] == "page"


def test_start_needs_an_operator_name_and_records_it():
    control, journal = _control()
    out: dict = {}
    thread = threading.Thread(target=lambda: out.setdefault("operator", control.wait_start("Start?")))
    thread.start()
    while control.live.get("prompt") is None:
        time.sleep(0.01)
    qid = control.live.get("prompt")["id"]
    with pytest.raises(PanelRequestError, match="operator's name"):
        control.answer(qid, True, operator="  ")
    control.answer(qid, True, operator="K. Lee")
    thread.join(5)
    assert out["operator"] == "K. Lee" and journal[0]["operator"] == "K. Lee"


def test_yes_answers_procedure_prompts_but_not_a_page_pause():
    control, journal = _control(operator="bot", yes=True)
    control.on_engine_event("message", {"message": m.Prompt("upload", "Upload?", {"new_sha256": "x"})})
    assert control.confirm("Upload?") is True
    control.on_engine_event("paused", {"message": "MoveLegs"})
    assert control.confirm("Paused: motion stopped. Continue the run?") is False  # Ctrl-C unattended: abort
    answers = [(e["key"], e["via"], e["answer"]) for e in journal]
    assert answers == [("upload", "--yes", True), ("pause", "--yes", False)]


def test_pause_is_refused_when_no_run_is_moving():
    control, _ = _control()
    with pytest.raises(PanelRequestError, match="not running"):
        control.pause()
    with pytest.raises(PanelRequestError, match="not paused"):
        control.continue_run()


# ------------------------------------------------------------------ HTTP rules


def _client(ctx: PanelContext, token: str | None, base: str) -> TestClient:
    return TestClient(build_app(ctx, token=token, loopback_only=token is None), base_url=base)


def test_loopback_panel_rejects_other_host_names_and_cross_site_commands():
    ctx = PanelContext(LiveState())
    client = _client(ctx, None, "http://127.0.0.1:8765")
    assert client.get("/api/state").status_code == 200
    assert client.get("/api/state", headers={"Host": "attacker.example:8765"}).status_code == 421
    assert client.post("/api/close").status_code == 403
    headers = {"X-Hilcal-Panel": "1", "Origin": "http://attacker.example"}
    assert client.post("/api/close", headers=headers).status_code == 403
    ok = client.post("/api/close", headers={"X-Hilcal-Panel": "1", "Origin": "http://127.0.0.1:8765"})
    assert ok.status_code == 200 and ctx.closed.is_set()


def test_a_panel_on_another_address_wants_the_token_on_every_request():
    ctx = PanelContext(LiveState())
    client = _client(ctx, "s3cret-token", "http://192.0.2.10:8765")
    assert client.get("/").status_code == 401
    assert client.get("/api/state", headers={"X-Hilcal-Token": "wrong"}).status_code == 401
    assert client.post("/api/close", headers={"X-Hilcal-Panel": "1"}).status_code == 401
    page = client.get("/?token=s3cret-token")
    assert page.status_code == 200 and "hilcal" in page.text
    assert "hilcal_panel_token" in page.headers["set-cookie"] and "HttpOnly" in page.headers["set-cookie"]
    assert client.get("/api/state").status_code == 200  # the cookie now carries it
    fresh = _client(ctx, "s3cret-token", "http://192.0.2.10:8765")
    assert fresh.get("/api/state", headers={"X-Hilcal-Token": "s3cret-token"}).status_code == 200


def test_commands_without_a_run_and_bad_bodies_change_nothing():
    ctx = PanelContext(LiveState())
    client = _client(ctx, None, "http://127.0.0.1")
    headers = {"X-Hilcal-Panel": "1"}
    assert client.post("/api/pause", headers=headers).status_code == 404
    control, _ = _control()
    ctx.control = control
    assert client.post("/api/questions/1", headers=headers, content=b"not json").status_code == 400
    assert client.post("/api/questions/1", headers=headers, json={"answer": "yes"}).status_code == 400
    assert client.post("/api/questions/1", headers=headers, json={"answer": True}).status_code == 409
    assert client.post("/api/continue", headers=headers).status_code == 409


def test_history_lists_runs_and_uploads_and_serves_only_known_report_files(tmp_path):
    run_dir = tmp_path / "run1"
    run_dir.mkdir()
    (run_dir / "report.html").write_text("<html><body>report of run1</body></html>")
    (run_dir / "secret.txt").write_text("not served")
    with Records(tmp_path / "records.sqlite") as records:
        records.record_run("run1", started_at="2026-11-20T10:00:00+00:00", status="complete", robot_name="paper",
                           operator="J. Smith", out_dir=str(run_dir), verify_before={"max_position_mm": 1.9},
                           verify_after={"max_position_mm": 0.004})
        records.record_upload({"outcome": "committed", "endpoint": "tcp://x:502", "params_sha256": "ab" * 32,
                               "started_at": "2026-11-20T10:05:00+00:00"}, "J. Smith", run_id="run1")
    ctx = PanelContext(LiveState(), records_path=tmp_path / "records.sqlite")
    client = _client(ctx, None, "http://127.0.0.1")
    entries = client.get("/api/history").json()["entries"]
    (run,) = entries
    assert run["run_id"] == "run1" and run["files"] == ["report.html"]
    assert run["uploads"][0]["outcome"] == "committed" and run["verify_after"]["max_position_mm"] == 0.004
    assert "report of run1" in client.get("/runs/run1/report.html").text
    assert client.get("/runs/run1/secret.txt").status_code == 404
    assert client.get("/runs/run1/../run1/secret.txt").status_code == 404
    assert client.get("/runs/nope/report.html").status_code == 404
    empty = PanelContext(LiveState(), records_path=tmp_path / "none.sqlite")
    assert _client(empty, None, "http://127.0.0.1").get("/api/history").json()["entries"] == []


def test_server_streams_snapshot_then_changes_and_stops_promptly_with_a_browser_attached():
    live = LiveState()
    server = PanelServer(PanelContext(live), "127.0.0.1", 0).start()
    try:
        with pytest.raises(PanelStartError, match="cannot listen"):
            PanelServer(PanelContext(LiveState()), "127.0.0.1", server.port)
        events: list[str] = []
        with httpx.stream("GET", f"http://127.0.0.1:{server.port}/api/events", timeout=5) as response:
            assert response.headers["content-type"].startswith("text/event-stream")
            for line in response.iter_lines():
                if line.startswith("data: "):
                    events.append(line[6:])
                    if len(events) == 1:
                        live.update("progress", done=7)
                    else:
                        break
        assert json.loads(events[0])["sections"]["run"]["status"] == "idle"
        change = json.loads(events[1])
        assert change["section"] == "progress" and change["value"] == {"done": 7}
        hanging = threading.Thread(target=_read_forever, args=(server.port,), daemon=True)
        hanging.start()
        while live.listeners == 0:
            time.sleep(0.01)
    finally:
        t0 = time.monotonic()
        server.stop()
        assert time.monotonic() - t0 < 4.0


def _read_forever(port: int) -> None:
    try:
        with httpx.stream("GET", f"http://127.0.0.1:{port}/api/events", timeout=30) as response:
            for _ in response.iter_lines():
                pass
    except httpx.HTTPError:
        pass


def test_a_server_on_another_address_prints_a_token_and_wants_it():
    server = PanelServer(PanelContext(LiveState()), "0.0.0.0", 0).start()
    try:
        assert server.token and f"?token={server.token}" in server.url
        base = f"http://127.0.0.1:{server.port}"
        assert httpx.get(f"{base}/api/state", timeout=5).status_code == 401
        assert httpx.get(f"{base}/api/state?token={server.token}", timeout=5).status_code == 200
    finally:
        server.stop()
    loopback = PanelServer(PanelContext(LiveState()), "127.0.0.1", 0)
    try:
        assert loopback.token is None and loopback.url == f"http://127.0.0.1:{loopback.port}/"
    finally:
        loopback.stop()


def test_hilcal_panel_serves_the_history_until_ctrl_c(tmp_path):
    with Records(tmp_path / "records.sqlite") as records:
        records.record_run("run7", started_at="2026-11-20T10:00:00+00:00", status="interrupted", operator="K. Lee")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cmd = [sys.executable, "-m", "procedures.cli", "panel", "--records", str(tmp_path / "records.sqlite"),
           "--port", str(port)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                history = httpx.get(f"http://127.0.0.1:{port}/api/history", timeout=2).json()
                break
            except httpx.HTTPError:
                assert time.monotonic() < deadline and proc.poll() is None, "hilcal panel did not start"
                time.sleep(0.1)
        assert [e["run_id"] for e in history["entries"]] == ["run7"]
        assert httpx.get(f"http://127.0.0.1:{port}/api/state", timeout=2).json()["sections"]["run"]["mode"] == "history"
        headers = {"X-Hilcal-Panel": "1"}
        assert httpx.post(f"http://127.0.0.1:{port}/api/abort", headers=headers, timeout=2).status_code == 404
        proc.send_signal(signal.SIGINT)
        assert proc.wait(15) == 0
        assert f"http://127.0.0.1:{port}/" in proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)


@pytest.mark.slow
def test_diagnosis_of_a_past_run_from_the_panel(tmp_path):
    from procedures.journal import Journal

    folder = tmp_path / "run1"
    folder.mkdir()
    done = subprocess.run([sys.executable, "-m", "procedures.cli", "simulate", "--out", str(folder / "recording.csv")],
                          capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    with Journal(folder / "journal.sqlite") as journal:
        journal.start("run1", "0" * 64, "{}", {"robot_path": None})
    with Records(tmp_path / "records.sqlite") as records:
        records.record_run("run1", started_at="2026-11-20T10:00:00+00:00", status="complete", out_dir=str(folder))
    live = LiveState()
    ctx = PanelContext(live, records_path=tmp_path / "records.sqlite")
    client = _client(ctx, None, "http://127.0.0.1")
    headers = {"X-Hilcal-Panel": "1"}
    live.set("run", {"mode": "run", "status": "running"})
    assert client.post("/api/runs/run1/diagnose", headers=headers).status_code == 409
    live.set("run", {"mode": "history", "status": "history"})
    assert client.post("/api/runs/nope/diagnose", headers=headers).status_code == 404
    assert client.post("/api/runs/run1/diagnose", headers=headers).status_code == 200
    ctx.diagnosis.join(120)
    diagnosis = live.get("diagnosis")
    assert diagnosis["status"] == "done", diagnosis
    assert diagnosis["effect"] and diagnosis["before"]["max_position_mm"] > 0
    page = client.get("/runs/run1/diagnosis/index.html")
    assert page.status_code == 200 and diagnosis["effect"] in page.text
