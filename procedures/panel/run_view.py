"""What the engine does, as the panel's sections: plan, progress and time estimate, measurements, identification, and
an adaptive run's decisions.

`RunView.on_engine_event` is an engine observer (see `procedures.engine.EngineObserver`): it reads the
messages the procedure yields and their results, and never talks to a device. Each measurement is shown
as its measured-vs-commanded pose error the moment the engine has journaled it. An adaptive run's measure poses are
not known in advance: each decision (``procedures.adaptive.progress``, a checkpoint) adds the next pose to the plan and
brings the predicted accuracy and the forecast remaining time.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from hilcal.metrics import pose_errors
from hilcal.reports.upload import upload_facts
from procedures import messages as m
from procedures.adaptive import PROGRESS_LABEL
from procedures.calibration_procedure import PRE_PHASES

LABEL = re.compile(r"^(?P<phase>[a-z_]+) (?P<pose>\d+) (?P<step>[a-z_]+)$")
PHASE_TITLES = {"measure": "measurement poses", "verify": "verification poses, before calibration",
                "verify_after": "verification poses, after calibration",
                "acceptance": "ISO 9283 acceptance test, after calibration"}
PLAN_PHASE = {"measure": "measure", "verify": "verify", "verify_after": "verify"}
ACTIVITY = {"PrepareCmm": "homing the CMM", "ReadParams": "reading the controller parameters",
            "ReadLegs": "reading the leg lengths", "Enable": "servo on", "Disable": "servo off",
            "Settle": "settling", "Upload": "uploading the parameter set (transaction with read-back)",
            "Prompt": "waiting for the operator"}

RemainingEstimate = Callable[[int, int, float], float | None]
"""(poses done in this session, poses left, seconds since this session started) -> seconds left, or None."""


def ratio_estimate(done_here: int, left: int, elapsed_s: float) -> float | None:
    """Seconds left at the rate of this session so far: elapsed / done x left (None before the first pose)."""
    if done_here <= 0:
        return None
    return elapsed_s / done_here * left


def measurement_item(row: dict[str, Any]) -> dict[str, Any]:
    """A journal measurement row as the panel shows it: its pose error, measured vs commanded."""
    meas = np.asarray(row["meas"], dtype=float)
    cmd = np.asarray(row["cmd"], dtype=float)
    position_mm, orientation_deg = pose_errors(meas[None, :], cmd[None, :])
    return {"phase": row["phase"], "index": int(row["index"]), "seq": int(row["seq"]), "time_s": row["time_s"],
            "position_error_mm": float(position_mm[0]), "orientation_error_deg": float(orientation_deg[0]),
            "cmd": cmd, "meas": meas, "sphere_fit_rms_mm": row.get("detail", {}).get("sphere_fit_rms_mm")}


class RunView:
    """Turns engine events into panel sections; `show_plan` first so progress knows the total."""

    def __init__(self, live: Any, estimate: RemainingEstimate = ratio_estimate,
                 estimate_basis: str = "elapsed / poses done in this session x poses left") -> None:
        self.live = live
        self.estimate = estimate
        self.estimate_basis = estimate_basis
        self.total = 0
        self._poses: dict[str, np.ndarray] = {}
        self._done: set[tuple[str, int]] = set()
        self._session_t0: float | None = None
        self._session_epoch: float | None = None
        self._done_here = 0
        self._current: object | None = None
        self._progress: dict[str, Any] = {}
        self._after_measure = 0
        self._measure_rows: int | None = None
        """An adaptive run's measure rows as forecast (None: the plan's)."""
        self._forecasting = False
        """In an adaptive measure phase: the remaining time is the forecast's, not the ratio's."""
        self._history: list[dict[str, Any]] = []

    def show_plan(self, plan: Any, robot: Any, acceptance_poses: int = 0, adaptive: dict | None = None) -> None:
        """The plan; `acceptance_poses` measurements of an acceptance test count in the progress too. An adaptive run
        (`adaptive`: its options and best case) shows its measure poses as it chooses them."""
        measure = np.zeros((0, 6)) if adaptive else plan.poses("measure")
        self._poses = {"measure": measure, "verify": plan.poses("verify")}
        self._after_measure = 2 * len(plan.verify_poses) + acceptance_poses
        self._measure_rows = None if not adaptive else int(adaptive.get("best_rows") or 0)
        self.total = (len(plan.measure_poses) if not adaptive else self._measure_rows) + self._after_measure
        self.live.set("plan", {"robot": robot.name, "sha256": plan.sha256(), "measure": measure,
                               "verify": self._poses["verify"], "workspace": robot.workspace, "home": robot.home,
                               "settle_s": plan.settle_s, "approach_mm": plan.approach_mm, "seed": plan.seed,
                               "adaptive": adaptive})
        self.live.set("adaptive", None if not adaptive else {"options": adaptive, "n_rows": 0})

    # ------------------------------------------------------------------ engine events

    def on_engine_event(self, kind: str, data: dict[str, Any]) -> None:
        if kind == "message":
            self._on_message(data["message"])
        elif kind == "done":
            self._on_done(data["message"], data["result"])
        elif kind == "paused":
            self.live.update("run", status="paused")
            self._set_progress(activity="paused: motion stopped")
        elif kind == "resumed":
            self.live.update("run", status="running")
            self.live.note("continued after the pause")
        elif kind == "stopped":
            self.live.note(f"motion stopped: {data.get('reason')}", "warn")
            if isinstance(self._current, m.Measure | m.PrepareCmm):
                self.live.update("cmm", last_error=data.get("reason"), last_error_at=time.time())

    def _on_message(self, msg: object) -> None:
        self._current = msg
        if self._session_t0 is None:
            self._session_t0, self._session_epoch = time.monotonic(), time.time()
            self.live.update("run", status="running")
        if isinstance(msg, m.MoveLegs):
            match = LABEL.match(msg.label)
            if match is None:
                self._set_progress(activity=f"moving ({msg.label})")
            else:
                self._at_pose(match["phase"], int(match["pose"]) - 1, f"moving ({match['step']})")
        elif isinstance(msg, m.Measure):
            self._at_pose(msg.phase, msg.index, "measuring the pose")
        elif isinstance(msg, m.PrepareCmm):
            self.live.update("cmm", session="starting")
            self._set_progress(activity=ACTIVITY["PrepareCmm"])
        elif isinstance(msg, m.Checkpoint):
            self._on_checkpoint(msg)
        elif type(msg).__name__ in ACTIVITY:
            self._set_progress(activity=ACTIVITY[type(msg).__name__])

    def _on_done(self, msg: object, result: Any) -> None:
        if isinstance(msg, m.Measure):
            self._add_rows([result], fresh=True)
            self.live.update("cmm", session="ready", last_pose_at=time.time())
        elif isinstance(msg, m.Recall):
            self._add_rows(result, fresh=False)
            if set(msg.phases) == set(PRE_PHASES):
                self._set_progress(activity="identifying (least squares and L-infinity)")
        elif isinstance(msg, m.PrepareCmm):
            self.live.update("cmm", session="ready", homed_at=time.time())
            self.live.note("measuring instrument ready (CMM homed, or laser tracker initialised)")
        elif isinstance(msg, m.Upload):
            facts = upload_facts(result)
            self.live.set("upload", {"outcome": result.get("outcome"), "sha256": result.get("sha256"),
                                     "record": result.get("record"), "save_record": result.get("save_record"),
                                     "summary": facts.summary() if facts else None,
                                     "sentences": facts.sentences() if facts else []})
            self.live.note(f"parameter upload: {facts.summary() if facts else result.get('outcome')}")
        elif isinstance(msg, m.ReadParams):
            self.live.note(f"controller parameters read ({msg.key})")

    def _on_checkpoint(self, msg: m.Checkpoint) -> None:
        data = msg.data or {}
        if msg.label in ("identified", "refused") and "identification" in data:
            self.live.set("identification", {**data["identification"], "status": msg.label,
                                             "mode": data.get("mode"), "problems": data.get("problems", [])})
            self.live.note("identification refused: " + "; ".join(data.get("problems", []))
                           if msg.label == "refused" else "identification done", "warn" if msg.label == "refused"
                           else "info")
        elif msg.label == "complete":
            self._set_progress(activity="verification done; writing the report")
        elif msg.label == PROGRESS_LABEL:
            self._on_decision(data)

    def _on_decision(self, data: dict[str, Any]) -> None:
        """An adaptive run's decision: its prediction in the history, the next pose in the plan, the forecast."""
        p, stop = data.get("prediction"), data.get("stop")
        if p is not None and all(h["n_rows"] != data["n_rows"] for h in self._history):
            self._history.append({"n_rows": data["n_rows"], "max_mm": p["max_mm"], "low_mm": p["low_mm"],
                                  "upper_mm": p["upper_mm"]})
        options = (self.live.get("adaptive") or {}).get("options")
        self.live.set("adaptive", {**data, "options": options, "history": self._history})
        nxt = data.get("next")
        poses = np.array([*data["poses"], *([nxt["pose"]] if nxt else [])], dtype=float).reshape(-1, 6)
        self._poses["measure"] = poses
        self.live.update("plan", measure=poses)
        ahead = 0 if stop else ((data.get("forecast") or {}).get("n_rows") or 0)
        self._measure_rows = data["n_rows"] + ahead
        self.total = self._measure_rows + self._after_measure
        self._forecasting = stop is None
        if stop is not None:
            self.live.note(f"adaptive plan stopped after {data['n_rows']} rows ({stop['kind']}): {stop['sentence']}")
            self._set_progress(activity="measure phase done: " + stop["kind"].replace("_", " "))
            return
        span = data.get("remaining_measure_range_s")
        after = data["after_measure_s"]
        self._set_progress(
            remaining_s=data.get("remaining_s"), updated_at=time.time(),
            remaining_range_s=None if span is None else [span[0] + after, span[1] + after],
            remaining_basis=f"the adaptive plan's forecast: {ahead} more measure rows, then the verify phases "
                            "(machine-time estimate)" if span is None else "no noise known before the repeats: "
                            "best case to budget (machine-time estimate)")

    # ------------------------------------------------------------------ progress

    def _add_rows(self, rows: list[dict[str, Any]], fresh: bool) -> None:
        for row in rows:
            key = (row["phase"], int(row["index"]))
            if key in self._done:
                continue
            self._done.add(key)
            self._done_here += int(fresh)
            self.live.append("measurements", measurement_item(row))
        self._set_progress()

    def _at_pose(self, phase: str, index: int, activity: str) -> None:
        poses = self._poses.get(PLAN_PHASE.get(phase, phase))
        target = poses[index].tolist() if poses is not None and 0 <= index < len(poses) else None
        size = self._measure_rows if phase == "measure" and self._measure_rows is not None else (
            None if poses is None else len(poses))
        self._set_progress(phase=phase, phase_title=PHASE_TITLES.get(phase, phase), pose=index + 1,
                           poses_in_phase=size, target=target, activity=activity)

    def _set_progress(self, **fields: Any) -> None:
        """Publish progress when something an operator reads changed; the estimate is redone per pose done."""
        before = dict(self._progress)
        self._progress.update(fields)
        self._progress["session_started_at"] = self._session_epoch
        done = len(self._done)
        if done != before.get("done") or "remaining_s" not in before or self.total != before.get("total"):
            self._progress.update(done=done, total=self.total)
            if not self._forecasting:
                elapsed = 0.0 if self._session_t0 is None else time.monotonic() - self._session_t0
                left = max(self.total - done, 0)
                self._progress.update(remaining_s=self.estimate(self._done_here, left, elapsed) if left else 0.0,
                                      remaining_basis=self.estimate_basis, remaining_range_s=None,
                                      updated_at=time.time())
        if self._progress != before:
            self.live.set("progress", self._progress)
