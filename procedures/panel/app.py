"""The panel's web application (Starlette): the page, its live stream, the operator's commands, history.

Routes: `/` the page (static files shipped in the package, nothing fetched from elsewhere), `/api/state`
(snapshot), `/api/events` (server-sent events: the snapshot, then every change), `POST /api/questions/ID`,
`/api/pause`, `/api/continue`, `/api/abort`, `/api/close`, `/api/history`, `/api/drift?machine=M` (a machine's
drift with trend plots), `/runs/RUN/FILE` (a run's
report files) and `POST /api/runs/RUN/diagnose`. No route sends anything to a device: answers go to the
engine, which applies the same checks as the command line (plausibility, the upload transaction).
"""

from __future__ import annotations

import asyncio
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from procedures.panel.control import OperatorControl, PanelRequestError
from procedures.panel.history import RUN_FILES, DiagnosisJobs, history, machine_drift, run_folder
from procedures.panel.live import LiveState
from procedures.panel.security import Guard

STATIC = Path(__file__).parent / "static"
KEEPALIVE_S = 10.0
ACTIVE = ("starting", "waiting to start", "running", "paused")
"""Run states in which the panel refuses to close or to start a diagnosis."""


@dataclass
class PanelContext:
    """What the web application serves: the live state, the run's controls (None: history only), records."""

    live: LiveState
    control: OperatorControl | None = None
    records_path: str | Path | None = None
    """The records database: a SQLite path or a URL."""
    live_runs: dict[str, Path] = field(default_factory=dict)
    closed: threading.Event = field(default_factory=threading.Event)
    diagnosis: DiagnosisJobs | None = None

    def __post_init__(self) -> None:
        if self.diagnosis is None:
            self.diagnosis = DiagnosisJobs(self.live)


def _error(e: Exception, status: int) -> JSONResponse:
    return JSONResponse({"error": str(e)}, status_code=status)


async def _json_body(request: Request) -> dict[str, Any]:
    try:
        body = await request.json()
    except ValueError:
        raise PanelRequestError("the request body must be a JSON object", 400) from None
    if not isinstance(body, dict):
        raise PanelRequestError("the request body must be a JSON object", 400)
    return body


def build_app(ctx: PanelContext, *, token: str | None = None, loopback_only: bool = True) -> Guard:
    """The ASGI application for one panel, wrapped in the security guard."""

    async def page(request: Request) -> Response:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})

    async def state(request: Request) -> Response:
        return JSONResponse(ctx.live.snapshot())

    async def events(request: Request) -> Response:
        snap, queue = ctx.live.subscribe()

        async def stream():
            try:
                yield f"event: snapshot\ndata: {snap}\n\n"
                while True:
                    try:
                        item = await asyncio.wait_for(queue.get(), KEEPALIVE_S)
                    except TimeoutError:
                        yield ": keep-alive\n\n"
                        continue
                    if item is None:
                        yield "event: closed\ndata: {}\n\n"
                        return
                    yield f"data: {item}\n\n"
            finally:
                ctx.live.unsubscribe(queue)

        return StreamingResponse(stream(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})

    def _control() -> OperatorControl:
        if ctx.control is None:
            raise PanelRequestError("no run is being controlled by this panel (history only)", 404)
        return ctx.control

    def _client(request: Request) -> str | None:
        return None if request.client is None else f"{request.client.host}:{request.client.port}"

    async def answer(request: Request) -> Response:
        try:
            body = await _json_body(request)
            if not isinstance(body.get("answer"), bool):
                raise PanelRequestError("'answer' must be true or false", 400)
            result = _control().answer(int(request.path_params["qid"]), body["answer"], client=_client(request),
                                       operator=body.get("operator"), confirm_sha256=body.get("confirm_sha256"),
                                       plan=body.get("plan"))
        except PanelRequestError as e:
            return _error(e, e.status)
        return JSONResponse(result)

    def command(action: str):
        async def handler(request: Request) -> Response:
            try:
                control = _control() if action != "close" else None
                if action == "pause":
                    control.pause("page")
                elif action == "continue":
                    control.continue_run()
                elif action == "abort":
                    control.abort()
                elif action == "close":
                    if ctx.live.get("run").get("status") in ACTIVE:
                        raise PanelRequestError("the run is still going: abort it first")
                    ctx.closed.set()
            except PanelRequestError as e:
                return _error(e, e.status)
            return JSONResponse({"ok": True, "action": action})

        return handler

    async def history_api(request: Request) -> Response:
        limit = max(1, min(int(request.query_params.get("limit", "50")), 500))
        machine = request.query_params.get("machine") or None
        return JSONResponse(await run_in_threadpool(history, ctx.records_path, limit, machine))

    async def drift_api(request: Request) -> Response:
        machine = request.query_params.get("machine")
        if not machine:
            return _error(ValueError("give ?machine=NAME"), 400)
        try:
            return JSONResponse(await run_in_threadpool(machine_drift, ctx.records_path, machine))
        except LookupError as e:
            return _error(e, 404)
        except Exception as e:  # the records' own errors: unavailable, bad URL
            return _error(e, 503)

    async def run_file(request: Request) -> Response:
        name = request.path_params["name"]
        if name not in RUN_FILES:
            return _error(FileNotFoundError(f"no such run file {name!r}"), 404)
        folder = await run_in_threadpool(run_folder, ctx.records_path, ctx.live_runs, request.path_params["run_id"])
        if folder is None or not (folder / name).is_file():
            return _error(FileNotFoundError(f"run {request.path_params['run_id']} has no {name}"), 404)
        return FileResponse(folder / name, media_type=RUN_FILES[name], headers={"Cache-Control": "no-store"})

    async def diagnose(request: Request) -> Response:
        run_id = request.path_params["run_id"]
        if ctx.live.get("run").get("status") in ACTIVE:
            return _error(RuntimeError("not while the run is going: a diagnosis would compete with the machine's "
                                       "links for the CPU"), 409)
        folder = await run_in_threadpool(run_folder, ctx.records_path, ctx.live_runs, run_id)
        if folder is None:
            return _error(FileNotFoundError(f"unknown run {run_id}"), 404)
        try:
            ctx.diagnosis.start(run_id, folder)
        except FileNotFoundError as e:
            return _error(e, 404)
        except RuntimeError as e:
            return _error(e, 409)
        return JSONResponse({"ok": True, "run_id": run_id})

    routes = [
        Route("/", page),
        Route("/api/state", state),
        Route("/api/events", events),
        Route("/api/questions/{qid:int}", answer, methods=["POST"]),
        *[Route(f"/api/{a}", command(a), methods=["POST"]) for a in ("pause", "continue", "abort", "close")],
        Route("/api/history", history_api),
        Route("/api/drift", drift_api),
        Route("/api/runs/{run_id}/diagnose", diagnose, methods=["POST"]),
        Route("/runs/{run_id}/{name:path}", run_file),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ]
    return Guard(Starlette(routes=routes), token, loopback_only)
