"""The sign-off of a run: who calibrated which machine with which instrument, the figures with their uncertainty,
the ISO 9283 table and the verdict (report.json's sign-off keys); then the certificate files and the records.

The instrument's part of every figure's uncertainty is the CMM's stated uncertainty per sphere-centre coordinate, or
a laser tracker's MPE read as the expanded uncertainty U (k = 2) per coordinate of a measured point at its distance
from the tracker (``hilcal.acceptance.tracker_mpe``), carried through the pose registration.

``signoff_section`` turns what the run measured into those keys (the math is ``hilcal.acceptance``);
``write_certificate`` renders certificate.html from report.json alone (``hilcal.reports.certificate``) and prints it
to certificate.pdf (``procedures.pdf``), so ``hilcal certificate RUN_DIR`` regenerates both from the run folder.
"""

from __future__ import annotations

import datetime as dt
import itertools
import json
import subprocess
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from hilcal.acceptance.evaluation import evaluate_iso9283, limit_figures
from hilcal.acceptance.iso9283 import CYCLE_ORDER, DEFAULT_CYCLES, POSE_NAMES
from hilcal.acceptance.tracker_mpe import K_MPE, target_points_mm, target_uncertainty_mm, tracker_origin_mm
from hilcal.acceptance.uncertainty import (
    K_COVERAGE,
    accuracy_figures,
    cmm_pose_covariance,
    model_uncertainty,
    pooled_covariance,
    repeated_groups,
)
from hilcal.acceptance.verdict import RULES, check_limits, overall
from hilcal.robot import Robot
from procedures.acceptance import AcceptanceTest
from procedures.signoff import SignoffSettings

log = structlog.get_logger(__name__)

CERTIFICATE_FILES = ("certificate.html", "certificate.pdf")
SIM_CMM = "simulated CMM (hilcal sim)"
SIM_TRACKER = "simulated laser tracker (hilcal sim)"
MPE_READING = ("the maximum permissible error at a point's distance from the tracker, read as the expanded uncertainty "
               "U (k = 2) of each coordinate of the measured point")


@dataclass(frozen=True)
class SignoffContext:
    """What the run knows for its sign-off besides the measurements."""

    operator: str | None
    settings: SignoffSettings
    acceptance: AcceptanceTest | None = None
    sim: bool = False
    robot_path: str | None = None
    instrument_url: str | None = None
    """Where the instrument is: the CMM's URL, the tracker's host:port."""
    tracker: Any = None
    """The station's laser tracker (``procedures.sections.tracker.TrackerSection``) when it measured with one."""
    simulation: dict | None = None
    """What a --sim run's simulator simulated (``sim_devices.sim_config.simulation_summary``): its clock's scale."""


def certificate_number(run_id: str) -> str:
    """Unique per run (the run id holds the start time and a random part) and the same when regenerated."""
    return f"HILCAL-{run_id}"


def software_info() -> dict[str, Any]:
    """hilcal's version and the git revision of its source (None outside a git checkout), and local changes."""
    try:
        version = metadata.version("hilcal")
    except metadata.PackageNotFoundError:
        version = None
    source = Path(__file__).resolve().parents[1]

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(source), *args], capture_output=True, text=True, timeout=5.0,
                                  check=False)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    revision = git("rev-parse", "HEAD")
    changes = git("status", "--porcelain", "--untracked-files=no") if revision else None
    return {"name": "hilcal", "version": version, "git_revision": revision,
            "git_modified": None if changes is None else bool(changes)}


def _cmm_uncertainty(ctx: SignoffContext, robot: Robot) -> tuple[float | None, str | None]:
    """The CMM's stated expanded uncertainty U (k = 2) of a sphere-centre coordinate (mm) and where it comes from."""
    if ctx.settings.cmm.stated_uncertainty_mm is not None:
        if ctx.settings.cmm_uncertainty_source is not None:  # not from the station file: the simulator's
            return ctx.settings.cmm.stated_uncertainty_mm, (
                "as the simulated CMM states it: twice the standard deviation of one touch point's noise (a centre "
                "fitted from several touches scatters less)")
        return ctx.settings.cmm.stated_uncertainty_mm, "as the station file states it, from the CMM's own certificate"
    if robot.sphere_sigma_mm is not None:
        return K_COVERAGE * robot.sphere_sigma_mm, "twice the sphere-centre standard deviation the robot file gives"
    return None, None


def _tracker(ctx: SignoffContext, robot: Robot, finished_at: str) -> tuple[dict[str, Any], np.ndarray]:
    """A laser tracker's instrument keys (its MPE, the U it gives the targets at the home pose) and pose covariance."""
    t = ctx.tracker
    platform, base = t.layouts()
    origin = tracker_origin_mm(t.alignment_matrix())
    u = target_uncertainty_mm(platform, base, robot.home, origin, t.mpe_constant_um, t.mpe_per_m_um)
    far = np.linalg.norm(target_points_mm(platform, base, robot.home) - origin, axis=1)
    due = t.calibration_due
    overdue = None if due is None else due < dt.datetime.fromisoformat(finished_at).date()
    warning = (f"the laser tracker's own calibration was due on {due.isoformat()}: overdue on the day of this "
               "calibration") if overdue else None
    return {"kind": "tracker", "cmm": None, "tracker": t.identity or (SIM_TRACKER if ctx.sim else None),
            "url": ctx.instrument_url, "mpe_constant_um": t.mpe_constant_um, "mpe_per_m_um": t.mpe_per_m_um,
            "mpe_reading": MPE_READING, "k": K_MPE, "stated_uncertainty_mm": None,
            "point_uncertainty_mm": {"min": float(np.min(u)), "max": float(np.max(u))},
            "target_distance_mm": {"min": float(np.min(far)), "max": float(np.max(far))},
            "n_platform_targets": len(platform), "n_base_monuments": len(base),
            "uncertainty_source": "the simulated tracker's MPE, at the distances of its station" if ctx.sim else (
                "the MPE the station file states for the tracker, at the distances its alignment gives"),
            "air": t.environment.model_dump(),
            "calibration_due": None if due is None else due.isoformat(), "overdue": overdue,
            "warning": warning}, t.pose_covariance(robot)


def _instrument(ctx: SignoffContext, robot: Robot, finished_at: str) -> dict[str, Any]:
    stated, source = _cmm_uncertainty(ctx, robot)
    due = ctx.settings.cmm.calibration_due
    overdue = None if due is None else due < dt.datetime.fromisoformat(finished_at).date()
    warning = None
    if overdue:
        warning = f"the CMM's own calibration was due on {due.isoformat()}: overdue on the day of this calibration"
    elif stated is None:
        warning = "the CMM's uncertainty is not stated: the figures carry only the scatter of the run's repeated poses"
    return {"kind": "cmm", "cmm": ctx.settings.cmm.identity or (SIM_CMM if ctx.sim else None),
            "url": ctx.instrument_url,
            "stated_uncertainty_mm": stated, "uncertainty_source": source,
            "calibration_due": None if due is None else due.isoformat(), "overdue": overdue, "warning": warning}


def _environment(rows: list[dict], simulation: dict | None = None) -> dict[str, Any]:
    """The temperature readings during the measurements and the time they span (a simulated run's on the simulated
    machine's clock, which runs its time scale faster than the wall clock: a 4-minute run is hours of its time)."""
    temps = [r["detail"]["temp_c"] for r in rows if isinstance(r.get("detail", {}).get("temp_c"), int | float)]
    span_s = _measuring_span_s(rows)
    scale = None if simulation is None else simulation.get("time_scale")
    machine_s = None if span_s is None else span_s * (scale or 1.0)
    clock = {"measurements_span_s": span_s, "machine_span_s": machine_s, "time_scale": scale}
    if not temps:
        return {"temperature_c": None, **clock, "note": "not recorded (the station reports no temperature)"}
    note = "the controller's leg temperature readings during the measurements"
    if scale is not None and machine_s is not None:
        note = (f"the simulated controller's temperature readings, over {_duration(machine_s)} of the simulated "
                f"machine's time (its clock runs {scale:g} times faster than real time: {_duration(span_s)} here)")
    return {"temperature_c": {"mean": float(np.mean(temps)), "min": float(np.min(temps)), "max": float(np.max(temps)),
                              "n": len(temps)}, **clock, "note": note}


def _measuring_span_s(rows: list[dict]) -> float | None:
    """Wall-clock seconds from the first measurement to the last, summed over the sessions of a resumed run (each
    session's engine clock starts at zero: a reading earlier than the one before starts a new session)."""
    times = [float(r["time_s"]) for r in sorted(rows, key=lambda r: r.get("seq", 0))
             if isinstance(r.get("time_s"), int | float)]
    if len(times) < 2:
        return None
    span, start = 0.0, times[0]
    for previous, now in itertools.pairwise(times):
        if now < previous:
            span, start = span + previous - start, now
    return span + times[-1] - start


def _duration(seconds: float | None) -> str:
    """12 s, 4.2 min, 6.4 h."""
    if seconds is None:
        return "–"
    if seconds < 120:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.1f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"


def _arrays(rows: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    return (np.array([r["meas"] for r in rows], dtype=float).reshape(-1, 6),
            np.array([r["cmd"] for r in rows], dtype=float).reshape(-1, 6))


def _iso_section(test: AcceptanceTest | None, rows: list[dict], cmm_cov: np.ndarray | None) -> tuple[dict | None, list]:
    if test is None:
        return None, []
    _, which_route = test.route()
    which = np.array([which_route[r["index"]] for r in rows], dtype=int)
    meas, _ = _arrays(rows)
    results = evaluate_iso9283(np.array(test.poses), meas, which, cmm_cov, seed=3)
    notes = []
    if test.cycles < DEFAULT_CYCLES:
        notes.append(f"{test.cycles} cycles: fewer than the {DEFAULT_CYCLES} of ISO 9283")
    return {"standard": "ISO 9283:1998", "sha256": test.sha256(), "cycles": test.cycles,
            "order": [POSE_NAMES[k] for k in CYCLE_ORDER],
            "cube": {"centre_mm": test.cube_centre_mm, "side_mm": test.cube_side_mm,
                     "orientation_deg": test.orientation_deg},
            "poses": [r.as_json() for r in results], "notes": notes}, results


def _model_spread(robot: Robot, plan: Any, result: Any) -> dict[str, Any] | None:
    """The uploaded geometry's covariance carried to the approval's 64 workspace poses (None without one), and
    whether its model is incomplete (its misfit is then in the covariance, ``hilcal.misfit``)."""
    from procedures.approval import model_covariance, model_misfit, workspace_samples

    if not result.outcomes:
        return None
    covariance, _ = model_covariance(result.outcomes[result.chosen], result.chosen, result.physics)
    if covariance is None or not np.all(np.isfinite(covariance)):
        return None
    misfit = model_misfit(result.outcomes[result.chosen], result.physics)
    return {**model_uncertainty(robot, covariance, workspace_samples(robot, plan.seed + 1)).as_json(),
            "model_incomplete": None if misfit is None else misfit.incomplete,
            "model_incomplete_note": "" if misfit is None else misfit.sentence("the parameters")}


def signoff_section(ctx: SignoffContext, robot: Robot, plan: Any, result: Any, pre_rows: list[dict],
                    run_id: str, finished_at: str) -> dict[str, Any]:
    """report.json's sign-off keys: operator, station, machine, software, instrument, environment, method,
    uncertainty, iso9283 and certificate (number, verdict per limit, decision rule)."""
    if ctx.tracker is not None:
        instrument, cmm_cov = _tracker(ctx, robot, finished_at)
    else:
        instrument = _instrument(ctx, robot, finished_at)
        stated = instrument["stated_uncertainty_mm"]
        cmm_cov = None if stated is None else cmm_pose_covariance(robot, stated / K_COVERAGE)
    measure = [r for r in pre_rows if r["phase"] == "measure"]
    verify = [r for r in pre_rows if r["phase"] == "verify"]
    groups = []
    for rows in (measure, result.acceptance_rows):  # never verify with verify_after: same command, other parameters
        meas, cmd = _arrays(rows)
        groups += repeated_groups(cmd, meas)
    rep_cov, rep_dof = pooled_covariance(groups)
    parts = [c for c in (cmm_cov, rep_cov) if c is not None]
    cov = sum(parts) if parts else None
    before = accuracy_figures(*_arrays(verify), cov, seed=1) if verify else None
    after = accuracy_figures(*_arrays(result.after_rows), cov, seed=2) if result.after_rows else None
    iso, iso_results = _iso_section(ctx.acceptance, result.acceptance_rows, cmm_cov)
    rule = ctx.settings.acceptance.decision_rule
    checks = check_limits(ctx.settings.acceptance.limits(), limit_figures(after, iso_results), rule)
    warnings = [w for w in (instrument["warning"],) if w]
    if ctx.settings.acceptance.needs_iso9283() and ctx.acceptance is None:
        warnings.append("the station sets ISO 9283 limits but the run had no acceptance test (--acceptance iso9283)")
    ident = result.outcomes[result.chosen].identification if result.outcomes else None
    return {
        "operator": ctx.operator,
        "station": {"name": ctx.settings.name or ("simulated station" if ctx.sim else None),
                    "file": ctx.settings.station_file, "simulated": ctx.sim},
        "machine": {"robot_name": robot.name, "robot_file": ctx.robot_path or "the built-in paper Table 1 robot",
                    "serial": ctx.settings.machine_serial},
        "software": software_info(),
        "instrument": instrument,
        "environment": _environment([*pre_rows, *result.after_rows, *result.acceptance_rows], ctx.simulation),
        "method": {"model": None if ident is None else ident.model, "estimator": result.chosen,
                   "effects": [] if result.physics is None or result.block is None else [
                       c.title for c in result.physics.loadable.corrected],
                   "plan_sha256": plan.sha256(), "n_measure_rows": len(measure), "n_verify_poses": len(verify),
                   "plan": "fixed" if not result.adaptive else "adaptive",
                   "adaptive_stop": None if not result.adaptive else {
                       k: result.adaptive.get(k) for k in ("kind", "title", "summary", "prediction", "verification")},
                   "acceptance_sha256": None if ctx.acceptance is None else ctx.acceptance.sha256()},
        "uncertainty": {
            "k": K_COVERAGE, "method": "GUM Supplement 1 Monte Carlo, seeded (docs/certificate.md)",
            "cmm_pose_sd": None if cmm_cov is None or ctx.tracker is not None else np.sqrt(np.diag(cmm_cov)).tolist(),
            "instrument_pose_sd": None if cmm_cov is None else np.sqrt(np.diag(cmm_cov)).tolist(),
            "repeatability_pose_sd": None if rep_cov is None else np.sqrt(np.diag(rep_cov)).tolist(),
            "repeatability_dof": rep_dof,
            "before": None if before is None else {k: f.as_json() for k, f in before.items()},
            "after": None if after is None else {k: f.as_json() for k, f in after.items()},
            "model_workspace": _model_spread(robot, plan, result),
        },
        "iso9283": iso,
        "certificate": {"number": certificate_number(run_id), "issued_at": finished_at,
                        "verdict": overall(checks), "limits": [c.as_json() for c in checks],
                        "decision_rule": {"key": rule, "text": RULES[rule]}, "warnings": warnings},
    }


def write_certificate(out_dir: Path, report: dict[str, Any]) -> tuple[Path, Path | None, str | None]:
    """certificate.html from report.json's content, then certificate.pdf; returns (html, pdf or None, problem)."""
    from hilcal.reports.certificate import certificate_html
    from procedures.pdf import PdfError, print_to_pdf

    html_path, pdf_path = out_dir / CERTIFICATE_FILES[0], out_dir / CERTIFICATE_FILES[1]
    html_path.write_text(certificate_html(report), encoding="utf-8")
    try:
        return html_path, print_to_pdf(html_path, pdf_path), None
    except PdfError as e:
        pdf_path.unlink(missing_ok=True)
        log.warning("certificate_pdf_failed", error=str(e))
        return html_path, None, f"certificate.pdf not written: {e}"


def regenerate_certificate(run_dir: Path) -> tuple[Path, Path | None, str | None]:
    """`hilcal certificate RUN_DIR`: both files again from the run's report.json; ValueError if it has no sign-off."""
    path = run_dir / "report.json"
    try:
        report = json.loads(path.read_text())
    except OSError as e:
        raise ValueError(f"{path}: cannot read: {e.strerror}") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not JSON: {e.msg} at line {e.lineno}") from None
    if not isinstance(report, dict) or not isinstance(report.get("certificate"), dict):
        raise ValueError(f"{path} has no certificate section (a run of an older hilcal, or not a complete run)")
    return write_certificate(run_dir, report)


def signoff_settings(options: dict[str, Any], station: Any | None) -> SignoffSettings:
    """The run's sign-off settings: the opened station's (a real run); for --sim the station file's where it gives
    them, else the simulated station's (``procedures.signoff.sim_signoff``; the file's alone without a station)."""
    from procedures.signoff import load_signoff, signoff_from_station, sim_signoff

    if not options.get("sim"):
        return signoff_from_station(station, options.get("station_path"))
    file = load_signoff(options.get("station_path"))
    return file if station is None else sim_signoff(file, station, options.get("station_path") is not None)


def verdict_line(report: dict[str, Any]) -> str:
    """The verdict in one line, with the limits that decided it."""
    cert = report.get("certificate") or {}
    failed = [c for c in cert.get("limits", []) if c["decision"] != "pass"]
    why = "; ".join(f"{c.get('label') or c['key']} {c['decision']}" + ("" if c["value"] is None else
                    f" ({c['where']}: {c['value']:.4g} ± {c['U']:.2g} {c['unit']} against {c['limit']:g})")
                    for c in failed)
    return f"acceptance verdict: {cert.get('verdict')}" + (f": {why}" if why else "")


def finish_certificate(out_dir: Path, report_path: Path) -> tuple[bool, Path, list[str]]:
    """Write the certificate of a complete run; (accepted, the file to file, lines for the operator).

    Accepted: the verdict is pass, or no limits were set. The file is the PDF, or the HTML if no PDF was made.
    """
    from hilcal.acceptance.verdict import NO_LIMITS

    report = json.loads(report_path.read_text())
    html_path, pdf_path, problem = write_certificate(out_dir, report)
    cert = report["certificate"]
    lines = [verdict_line(report), f"certificate {cert['number']}: {pdf_path or html_path}"]
    lines += [f"warning: {w}" for w in cert.get("warnings", [])]
    if problem:
        lines.append(f"warning: {problem}")
    return cert["verdict"] in ("pass", NO_LIMITS), pdf_path or html_path, lines


def record_signoff(recorder: Any, journal: Any, report_path: Path | None, certificate: Path | None) -> str | None:
    """Store the verdict and the certificate with the run in the records; a note if the records refuse them."""
    from procedures.records import RecordsError

    if report_path is None or certificate is None:
        return None
    report = json.loads(report_path.read_text())
    cert = report.get("certificate") or {}
    fields = {"verdict": cert.get("verdict"), "certificate_number": cert.get("number"),
              "certificate_path": str(certificate.resolve())}
    try:
        recorder.write(journal, run=fields)
    except RecordsError as e:
        log.warning("records_refused_signoff", error=str(e))
        return f"the records did not take the verdict ({e}); it is in report.json and the certificate"
    return None
