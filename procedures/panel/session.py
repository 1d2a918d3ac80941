"""One panel for one `hilcal run --panel` (or the history-only `hilcal panel`): server, live state, controls.

The runner calls it at its milestones: `run_opened` (plan, devices), `wait_start` (the operator starts the
run from the page or the terminal), `observer` goes to the engine, `finished` (result and report files),
then `linger` keeps the page up so the operator can read the report, and `close`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from procedures.panel.app import PanelContext
from procedures.panel.control import OperatorControl
from procedures.panel.history import RUN_FILES
from procedures.panel.live import LiveState
from procedures.panel.monitor import StationMonitor
from procedures.panel.run_view import RunView
from procedures.panel.server import DEFAULT_HOST, DEFAULT_PORT, PanelServer
from procedures.panel.terminal import TerminalInput


class PanelSession:
    """The panel of one run; `start()` returns the URL to print."""

    def __init__(self, *, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, operator: str | None = None,
                 yes: bool = False, records_path: str | Path | None = None, say: Callable[[str], None] = print,
                 terminal_fd: int | None = 0, history_only: bool = False) -> None:
        self.live = LiveState()
        self.view = RunView(self.live)
        self.control = None if history_only else OperatorControl(self.live, operator=operator, yes=yes, say=say)
        self.ctx = PanelContext(self.live, self.control, records_path)
        self.server = PanelServer(self.ctx, host, port)
        self.live.set("run", {"mode": "history" if history_only else "run",
                              "status": "history" if history_only else "starting"})
        use_terminal = self.control is not None and terminal_fd is not None
        self._terminal = TerminalInput(self.control.terminal_line, terminal_fd) if use_terminal else None
        self._monitor: StationMonitor | None = None

    @property
    def url(self) -> str:
        return self.server.url

    def start(self) -> str:
        self.server.start()
        if self._terminal is not None:
            self._terminal.start()
        return self.server.url

    # ------------------------------------------------------------------ runner milestones

    def observer(self, kind: str, data: dict[str, Any]) -> None:
        """The engine observer: the controls first (a pending pause is delivered here), then the view."""
        assert self.control is not None
        self.control.on_engine_event(kind, data)
        self.view.on_engine_event(kind, data)

    def confirm(self, text: str) -> bool:
        assert self.control is not None
        return self.control.confirm(text)

    def run_opened(self, *, run_id: str, plan: Any, robot: Any, out_dir: Path, journal: Any, devices: Any,
                   resumed: bool, acceptance_poses: int = 0, adaptive: dict | None = None) -> None:
        """The run's plan is known (`adaptive`: an adaptive run's options and best case, see RunView.show_plan)."""
        assert self.control is not None
        self.ctx.live_runs[run_id] = out_dir
        self.control.journal_event = journal.event
        self.view.show_plan(plan, robot, acceptance_poses, adaptive)
        self.live.update("run", run_id=run_id, robot=robot.name, out_dir=str(out_dir), resumed=resumed,
                         operator=self.control.operator, status="waiting to start")
        self._monitor = StationMonitor(self.live, devices).start()

    def wait_start(self, plan: dict[str, Any] | None = None,
                   check_plan: Callable[[dict[str, Any]], dict[str, Any]] | None = None) -> str:
        """The operator starts (or continues) the run; NotStarted if they decline. Returns their name.

        plan and check_plan: the measurement plan on the start form (see OperatorControl.wait_start); the one chosen
        there is `start_plan` afterwards (None: unchanged)."""
        assert self.control is not None
        run = self.live.get("run")
        verb = "Continue the interrupted" if run.get("resumed") else "Start the"
        operator = self.control.wait_start(f"{verb} calibration run {run.get('run_id')} on {run.get('robot')}?",
                                           plan, check_plan)
        self.live.update("run", operator=operator or None, status="running")
        return operator

    @property
    def start_plan(self) -> dict[str, Any] | None:
        """The plan chosen on the start form ({adaptive, target_mm, max_minutes}), None if the form did not set one."""
        return None if self.control is None else self.control.start_plan

    def finished(self, *, code: int, message: str, status: str, out_dir: Path | None,
                 report: dict[str, Any] | None) -> None:
        """The run's outcome and its files; the station monitor stops (the devices close next)."""
        self._stop_monitor()
        files = [] if out_dir is None else [n for n in RUN_FILES if (out_dir / n).is_file()]
        self.live.set("result", {"code": code, "message": message, "status": status, "files": files,
                                 "verification": None if report is None else report.get("verification"),
                                 "certificate": None if report is None else report.get("certificate"),
                                 "finished_at": time.time()})
        self.live.update("run", status=status)
        self.live.note(message, "info" if code == 0 else "warn")

    def linger(self, max_s: float, say: Callable[[str], None] = print) -> None:
        """Keep serving until the page's "Close panel", Ctrl-C, or max_s seconds."""
        say(f"the panel stays at {self.url} for up to {max_s / 60:.0f} min: close it on the page or press Ctrl-C")
        try:
            self.ctx.closed.wait(max_s)
        except KeyboardInterrupt:
            pass

    def _stop_monitor(self) -> None:
        if self._monitor is not None:
            self._monitor.stop()
            self._monitor = None

    def close(self) -> None:
        self._stop_monitor()
        if self._terminal is not None:
            self._terminal.stop()
        self.ctx.diagnosis.join(0.0)
        self.server.stop()


def serve_history(records_path: str | Path, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT,
                  say: Callable[[str], None] = print, stop: threading.Event | None = None) -> None:
    """`hilcal panel`: past runs, their reports and uploads, until Ctrl-C (or `stop` is set)."""
    session = PanelSession(host=host, port=port, records_path=records_path, history_only=True)
    url = session.start()
    from procedures.records import redact

    say(f"hilcal panel (history of {redact(str(records_path))}) at {url}  - Ctrl-C to stop")
    try:
        (stop or threading.Event()).wait()
    except KeyboardInterrupt:
        pass
    finally:
        session.close()
