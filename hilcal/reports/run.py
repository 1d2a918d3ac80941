"""The report of one `hilcal run`: report.json (machine contract) and a self-contained report.html.

Pure: the caller hands over everything that was measured, identified and uploaded; nothing here talks to a
device. The page follows the paper's section 5.3: absolute position and orientation errors at the
verification poses before and after calibration (Figs. 13 and 14) and the four indicators of Table 7
(maximum, range, average, RMS), plus the identified parameters, LS against L-infinity, the plausibility
check and what was uploaded. Plots are PNGs embedded as base64 data URIs, so the page opens offline.
"""

from __future__ import annotations

import html
import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hilcal.identification import IdentificationResult
from hilcal.metrics import AccuracySummary, Indicators
from hilcal.reports.adaptive import adaptive_html
from hilcal.reports.certificate import signoff_html
from hilcal.reports.drift import drift_html
from hilcal.reports.figures import fixed_margins, new_figure, plain_log_scale, png_base64
from hilcal.reports.physics import physics_html
from hilcal.reports.run_sections import (
    compensation_html,
    figures_sentence,
    links_html,
    links_lines,
    parameter_words,
    plausibility_html,
    simulation_html,
    stations_lines,
    upload_html,
)
from hilcal.reports.timing import time_html

INDICATORS = ("max", "range", "mean", "rms")
INDICATOR_LABELS = {"max": "maximum", "range": "range", "mean": "average", "rms": "RMS"}
TABLE7_ROWS = {"max": "maximum error", "range": "range of error", "mean": "average error",
               "rms": "root-mean-square error"}
ESTIMATOR_LABELS = {"ls": "least squares", "linf": "L-infinity"}
_LEG_NAME = re.compile(r"^leg(\d+)_(.+)$")


def _ordered(estimators: object) -> list[str]:
    """Estimator names in the paper's order: least squares, then L-infinity, then anything else."""
    rank = {"ls": 0, "linf": 1}
    return sorted(estimators, key=lambda e: (rank.get(e, 2), e))


@dataclass(frozen=True)
class RunReport:
    """Everything one calibration run produced; verification errors are measured poses vs commanded ones."""

    status: str
    run_id: str
    uploaded: bool
    estimator: str
    robot_name: str
    plan_sha256: str
    started_at: str
    finished_at: str
    verify_before: AccuracySummary
    verify_after: AccuracySummary | None
    per_pose_before: tuple[np.ndarray, np.ndarray]
    per_pose_after: tuple[np.ndarray, np.ndarray] | None
    identifications: dict[str, IdentificationResult]
    predicted_after: dict[str, AccuracySummary]
    chosen: str
    plausibility: dict
    compensation: dict
    upload: dict | None
    warnings: tuple[str, ...] = ()
    machine_time: dict | None = None
    """``hilcal.reports.timing.time_section``: estimated against actual time per phase."""
    links: dict | None = None
    """Per link (controller, cmm, modbus): holds, retakes, total and longest hold in s, lost or not."""
    drift: dict | None = None
    """``hilcal.drift.DriftResult.to_json()``: the machine's parameters since its earlier calibrations."""
    physics: dict | None = None
    """``procedures.physics.PhysicsDecision.to_json()``: what the run's diagnosis found and the upload corrected."""
    signoff: dict | None = None
    """report.json's sign-off keys (operator, station, machine, software, instrument, environment, method,
    uncertainty, iso9283, certificate): ``procedures.certificate.signoff_section``."""
    adaptive: dict | None = None
    """``hilcal.reports.adaptive.adaptive_section``: an adaptive run's stop reason, prediction and verification."""
    stations: dict | None = None
    """``drivers.tracker.station.stations_summary``: a laser tracker's stations and where it was set up again."""
    simulation: dict | None = None
    """A --sim run's simulated machine (``sim_devices.sim_config.simulation_summary``, with the run's timing)."""

    def __post_init__(self) -> None:
        if self.identifications and self.chosen not in self.identifications:
            raise ValueError(f"chosen estimator {self.chosen!r} is not among {sorted(self.identifications)}")
        _check_per_pose("per_pose_before", self.per_pose_before, self.verify_before)
        if (self.per_pose_after is None) != (self.verify_after is None):
            raise ValueError("verify_after and per_pose_after must both be given or both be None")
        if self.per_pose_after is not None and self.verify_after is not None:
            _check_per_pose("per_pose_after", self.per_pose_after, self.verify_after)


def _check_per_pose(what: str, per_pose: tuple[np.ndarray, np.ndarray], summary: AccuracySummary) -> None:
    """One error per measured verification pose; NaN marks a pose not measured (out of the machine's reach)."""
    position_mm, orientation_deg = (np.asarray(a, dtype=float) for a in per_pose)
    measured = int(np.isfinite(position_mm).sum()) if position_mm.ndim == 1 else -1
    if position_mm.ndim != 1 or orientation_deg.shape != position_mm.shape or measured != summary.n_poses:
        raise ValueError(f"{what}: expected two arrays with {summary.n_poses} errors (one per measured verification "
                         f"pose), got shapes {position_mm.shape} and {orientation_deg.shape} with {measured} measured")


# ------------------------------------------------------------------ JSON


def _jsonable(value: Any) -> Any:
    """Plain JSON types; NaN and infinities become None (strict JSON has neither)."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.bool_ | bool):
        return bool(value)
    if isinstance(value, np.integer | int):
        return int(value)
    if isinstance(value, np.floating | float):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "model_dump"):
        return _jsonable(value.model_dump())
    return value


def _reduction_percent(before: AccuracySummary, after: AccuracySummary) -> dict[str, dict[str, float | None]]:
    """(before - after) / before in percent per indicator, as the paper reports it."""
    out: dict[str, dict[str, float | None]] = {}
    for key in ("position_mm", "orientation_deg"):
        b: Indicators = getattr(before, key)
        a: Indicators = getattr(after, key)
        out[key] = {
            ind: (100.0 * (getattr(b, ind) - getattr(a, ind)) / getattr(b, ind)) if getattr(b, ind) else None
            for ind in INDICATORS
        }
    return out


def _std(ident: IdentificationResult) -> list[float | None]:
    if ident.std_errors is None:
        return [None] * len(ident.names)
    return [float(s) if math.isfinite(s) else None for s in ident.std_errors]


def _ls_vs_linf(r: RunReport) -> dict[str, Any]:
    estimators: dict[str, Any] = {}
    for est in _ordered(set(r.identifications) | set(r.predicted_after)):
        ident = r.identifications.get(est)
        predicted = r.predicted_after.get(est)
        estimators[est] = {
            "predicted_verification": predicted.brief() if predicted else None,
            "predicted_table7": predicted.full() if predicted else None,
            "fit": None if ident is None else {
                "max_abs_residual_mm": ident.max_abs_residual,
                "rms_residual_mm": ident.rms_residual,
                "sigma_mm": ident.sigma,
                "converged": ident.converged,
                "n_iterations": ident.n_iterations,
                "rank": ident.rank,
                "model": ident.model,
                "method": ident.method,
            },
            "parameters": None if ident is None else ident.parameters(),
        }
    comparison: dict[str, Any] = {"max_abs_parameter_difference_mm": None, "lower_predicted_max_position": None}
    ls, linf = r.identifications.get("ls"), r.identifications.get("linf")
    if ls is not None and linf is not None and ls.names == linf.names:
        comparison["max_abs_parameter_difference_mm"] = float(np.max(np.abs(ls.x - linf.x)))
    if r.predicted_after:
        comparison["lower_predicted_max_position"] = min(
            r.predicted_after, key=lambda e: r.predicted_after[e].position_mm.max
        )
    return {"estimators": estimators, "comparison": comparison}


def report_json(r: RunReport) -> dict[str, Any]:
    """The `hilcal run` report contract (strict JSON: NaN becomes null)."""
    ident = r.identifications.get(r.chosen)
    parameters = {} if ident is None else {
        name: {"value_mm": float(value), "std_mm": std}
        for name, value, std in zip(ident.names, ident.x, _std(ident), strict=True)
    }
    after = r.verify_after
    out = {
        "status": r.status,
        "run_id": r.run_id,
        "uploaded": r.uploaded,
        "estimator": r.estimator,
        "chosen": r.chosen,
        "verification": {"before": r.verify_before.brief(), "after": after.brief() if after else None},
        "table7": {
            "n_poses": r.verify_before.n_poses,
            "before": r.verify_before.full(),
            "after": after.full() if after else None,
            "reduction_percent": _reduction_percent(r.verify_before, after) if after else None,
            "predicted_after": {est: r.predicted_after[est].full() for est in _ordered(r.predicted_after)},
        },
        "per_pose": {
            "before": {"position_mm": r.per_pose_before[0], "orientation_deg": r.per_pose_before[1]},
            "after": None if r.per_pose_after is None else {
                "position_mm": r.per_pose_after[0], "orientation_deg": r.per_pose_after[1]},
        },
        "parameters": parameters,
        "ls_vs_linf": _ls_vs_linf(r),
        "plausibility": r.plausibility,
        "compensation": r.compensation,
        "physics": r.physics,
        "upload": r.upload,
        "plan_sha256": r.plan_sha256,
        "robot": {"name": r.robot_name},
        "times": {"started_at": r.started_at, "finished_at": r.finished_at},
        "warnings": list(r.warnings),
        "machine_time": r.machine_time,
        "links": r.links,
        "stations": r.stations,
        "drift": r.drift,
        "adaptive": r.adaptive,
        "simulation": r.simulation,
        **(r.signoff or {}),
    }
    return _jsonable(out)


# ------------------------------------------------------------------ plots


def _per_pose_plot(r: RunReport, which: int, label: str, unit: str) -> str:
    """Fig. 13 (which=0, position) or Fig. 14 (which=1, orientation): error per verification pose."""
    before = np.asarray(r.per_pose_before[which], dtype=float)
    poses = np.arange(1, before.size + 1)
    fig = new_figure(9, 3.8)
    ax = fig.subplots()
    ax.plot(poses, before, "o-", color="tab:red", label="before calibration (measured)")
    title = f"Absolute {label} error at the verification poses"
    if r.per_pose_after is not None:
        after = np.asarray(r.per_pose_after[which], dtype=float)
        chosen = ESTIMATOR_LABELS.get(r.chosen, r.chosen)
        ax.plot(poses, after, "s-", color="tab:blue", label=f"after calibration ({chosen}, measured)")
        if np.nanmin(after) > 0 and np.nanmax(before) / np.nanmax(after) > 20:
            plain_log_scale(ax)
            title += " (log scale)"
    predicted = r.predicted_after.get(r.chosen)
    if predicted is not None:
        bound = (predicted.position_mm if which == 0 else predicted.orientation_deg).max
        ax.axhline(bound, color="tab:blue", ls=":", label=f"predicted maximum after ({r.chosen})")
    ax.set_xlabel("verification pose (number)")
    ax.set_ylabel(f"{label} error ({unit})")
    ax.set_xticks(poses)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fixed_margins(fig, left_in=0.8, right_in=0.15, bottom_in=0.55, top_in=0.35)
    return png_base64(fig)


def _group_by_leg(names: tuple[str, ...]) -> dict[str, list[int]]:
    groups: dict[str, list[int]] = {}
    for k, name in enumerate(names):
        m = _LEG_NAME.match(name)
        groups.setdefault(f"leg {m.group(1)}" if m else "other", []).append(k)
    return groups


def _short(name: str) -> str:
    m = _LEG_NAME.match(name)
    rest = m.group(2) if m else name
    return rest.removesuffix("_mm").removesuffix("_rad")


def _unit(names: list[str]) -> str:
    units = {"mm" if n.endswith("_mm") else "rad" if n.endswith("_rad") else "?" for n in names}
    return units.pop() if len(units) == 1 else "mm or rad (see name)"


def _parameter_plot(r: RunReport) -> str | None:
    """Identified errors per leg: LS with ±2σ bars, L-infinity (no σ) as markers beside them."""
    if not r.identifications:
        return None
    ref = r.identifications.get("ls") or r.identifications[r.chosen]
    groups = _group_by_leg(ref.names)
    ncols = 3 if len(groups) > 1 else 1
    nrows = math.ceil(len(groups) / ncols)
    fig = new_figure(13, 3.3 * nrows)
    axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
    styles = {"ls": ("o", "tab:blue", -0.15), "linf": ("D", "tab:orange", 0.15)}
    for ax, (group, idx) in zip(axes, groups.items(), strict=False):
        xs = np.arange(len(idx))
        for est in _ordered(r.identifications):
            ident = r.identifications[est]
            if ident.names != ref.names:
                continue
            marker, color, shift = styles.get(est, ("^", "tab:green", 0.0))
            values = ident.x[idx]
            label = ESTIMATOR_LABELS.get(est, est) + (" (uploaded)" if est == r.chosen else "")
            if ident.std_errors is not None:
                ax.errorbar(xs + shift, values, yerr=2 * ident.std_errors[idx], fmt=marker, color=color,
                            capsize=3, ms=5, label=f"{label} ±2σ")
            else:
                ax.plot(xs + shift, values, marker, color=color, ms=5, label=f"{label} (no σ)")
        ax.axhline(0.0, color="k", lw=0.6)
        ax.set_xticks(xs, [_short(ref.names[k]) for k in idx], rotation=45, fontsize=8)
        ax.set_title(group)
        ax.set_ylabel(f"error ({_unit([ref.names[k] for k in idx])})")
        ax.grid(alpha=0.3)
    for ax in axes[len(groups):]:
        ax.set_visible(False)
    axes[0].legend(fontsize=7)
    fig.suptitle("Identified parameter errors (±2σ for least squares; L-infinity gives no σ)")
    fixed_margins(fig, left_in=0.8, right_in=0.15, bottom_in=0.6, top_in=0.65, wspace_in=0.85, hspace_in=0.95)
    return png_base64(fig)


def _comparison_plot(r: RunReport) -> str:
    """The four indicators before, predicted after (each estimator) and measured after."""
    series: list[tuple[str, AccuracySummary]] = [("before (measured)", r.verify_before)]
    series += [(f"predicted after, {ESTIMATOR_LABELS.get(e, e)}", r.predicted_after[e])
               for e in _ordered(r.predicted_after)]
    if r.verify_after is not None:
        series.append((f"after, {ESTIMATOR_LABELS.get(r.chosen, r.chosen)} (measured)", r.verify_after))
    fig = new_figure(12, 4)
    axes = fig.subplots(1, 2)
    width = 0.8 / len(series)
    xs = np.arange(len(INDICATORS))
    for ax, key, title in ((axes[0], "position_mm", "position error (mm)"),
                           (axes[1], "orientation_deg", "orientation error (deg)")):
        table = np.array([[getattr(getattr(s, key), ind) for ind in INDICATORS] for _, s in series])
        for j, (label, values) in enumerate(zip([lb for lb, _ in series], table, strict=True)):
            bars = ax.bar(xs + (j - (len(series) - 1) / 2) * width, values, width, label=label)
            ax.bar_label(bars, fmt="%.3g", fontsize=6, rotation=90, padding=2)
        log_scale = table.min() > 0 and table.max() / table.min() > 50
        if log_scale:
            plain_log_scale(ax)
        ax.margins(y=0.25)
        ax.set_xticks(xs, [INDICATOR_LABELS[i] for i in INDICATORS])
        ax.set_ylabel(title)
        ax.set_title(f"verification poses: {title}" + (" (log scale)" if log_scale else ""))
        ax.grid(alpha=0.3, axis="y")
    axes[0].legend(fontsize=8)
    fig.suptitle("Least squares against L-infinity: predicted verification indicators")
    fixed_margins(fig, left_in=0.85, right_in=0.15, bottom_in=0.4, top_in=0.75, wspace_in=1.0)
    return png_base64(fig)


# ------------------------------------------------------------------ HTML


def _esc(value: object) -> str:
    return html.escape(str(value), quote=True)


def _num(value: float | None, digits: int) -> str:
    return "n/a" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def _table7_html(r: RunReport) -> str:
    cols: list[tuple[str, AccuracySummary | None]] = [("before calibration (measured)", r.verify_before)]
    cols.append((f"after calibration, {ESTIMATOR_LABELS.get(r.chosen, r.chosen)} (measured)", r.verify_after))
    cols += [(f"predicted after, {ESTIMATOR_LABELS.get(e, e)}", r.predicted_after[e])
             for e in _ordered(r.predicted_after)]
    reduction = _reduction_percent(r.verify_before, r.verify_after) if r.verify_after else None
    head = "".join(f'<th colspan="2">{_esc(label)}</th>' for label, _ in cols)
    head += '<th colspan="2">reduction, measured (%)</th>'
    sub = "".join("<th>position (mm)</th><th>orientation (deg)</th>" for _ in range(len(cols) + 1))
    rows = ""
    for ind in INDICATORS:
        cells = ""
        for _, s in cols:
            if s is None:
                cells += "<td>n/a</td><td>n/a</td>"
            else:
                position, orientation = getattr(s.position_mm, ind), getattr(s.orientation_deg, ind)
                cells += f"<td>{_num(position, 4)}</td><td>{_num(orientation, 5)}</td>"
        for key in ("position_mm", "orientation_deg"):
            cells += f"<td>{_num(reduction[key][ind], 2) if reduction else 'n/a'}</td>"
        rows += f"<tr><th>{TABLE7_ROWS[ind]}</th>{cells}</tr>"
    return (f'<table class="t7"><tr><th rowspan="2">indicator</th>{head}</tr><tr>{sub}</tr>{rows}</table>'
            f"<p>{r.verify_before.n_poses} verification poses; errors are measured poses against commanded ones "
            "(predicted: the identified model on the before-calibration rows).</p>")


def _parameters_html(r: RunReport) -> str:
    if not r.identifications:
        return "<p>no identification</p>"
    ests = _ordered(r.identifications)
    ref = r.identifications[r.chosen]
    head = "".join(
        f"<th>{_esc(ESTIMATOR_LABELS.get(e, e))} value (mm)</th>"
        + ("<th>σ (mm)</th>" if r.identifications[e].std_errors is not None else "")
        for e in ests
    )
    rows = ""
    for k, name in enumerate(ref.names):
        cells = ""
        for e in ests:
            ident = r.identifications[e]
            cells += f"<td>{_num(float(ident.x[k]), 4)}</td>" if ident.names == ref.names else "<td>n/a</td>"
            if ident.std_errors is not None:
                cells += f"<td>{_num(float(ident.std_errors[k]), 4)}</td>"
        rows += f"<tr><th>{_esc(parameter_words(name))}</th>{cells}</tr>"
    fits = "".join(
        f"<li>{_esc(ESTIMATOR_LABELS.get(e, e))}: max |residual| {_num(r.identifications[e].max_abs_residual, 4)} "
        f"mm, RMS {_num(r.identifications[e].rms_residual, 4)} mm, rank {r.identifications[e].rank} (parameters "
        f"the poses determine), {'converged' if r.identifications[e].converged else 'NOT converged'}</li>"
        for e in ests
    )
    return (f"<ul>{fits}</ul><details><summary>all {len(ref.names)} values</summary>"
            f'<table><tr><th>parameter</th>{head}</tr>{rows}</table></details>')


_CSS = """body{font-family:sans-serif;max-width:1250px;margin:2em auto;padding:0 1em;color:#222}
img{max-width:100%;display:block;margin:1em 0}table{border-collapse:collapse;margin:.5em 0}
td,th{border:1px solid #ccc;padding:3px 8px;text-align:right;vertical-align:top}table.kv th{text-align:left}
.status{padding:.6em 1em;border-radius:4px;font-weight:bold}.ok{background:#dfd}.bad{background:#fdd}
.warn{background:#ffd;padding:.4em 1em}code{font-size:90%}"""


def report_html(r: RunReport) -> str:
    """The self-contained page: inline CSS, plots as data URIs, no external references."""
    def img(b64: str | None, alt: str) -> str:
        return "" if b64 is None else f'<img alt="{_esc(alt)}" src="data:image/png;base64,{b64}">'

    ok = r.status == "complete"
    warnings = "".join(f"<li>{_esc(w)}</li>" for w in r.warnings)
    after_brief = r.verify_after.brief() if r.verify_after else None
    headline = figures_sentence(r.verify_before.brief(), after_brief)
    estimators = (f"{ESTIMATOR_LABELS.get(r.estimator, r.estimator)} / "
                  f"{ESTIMATOR_LABELS.get(r.chosen, r.chosen) if r.chosen else 'none'}")
    return f"""<!doctype html><html lang="en"><head><meta charset="utf-8">
<title>hilcal run {_esc(r.run_id)}: {_esc(r.status)}</title><style>{_CSS}</style></head><body>
<h1>Calibration run {_esc(r.run_id)}</h1>
<p class="status {'ok' if ok else 'bad'}">status: {_esc(r.status)}; parameters uploaded: {'yes' if r.uploaded else 'no'}
</p>
{f'<div class="warn"><b>warnings</b><ul>{warnings}</ul></div>' if warnings else ''}
{signoff_html(r.signoff)}
<table class="kv"><tr><th>robot</th><td>{_esc(r.robot_name)}</td></tr>
<tr><th>plan SHA-256</th><td><code>{_esc(r.plan_sha256)}</code></td></tr>
<tr><th>estimator requested / uploaded</th><td>{_esc(estimators)}</td></tr>
<tr><th>started / finished (UTC)</th><td>{_esc(_when(r.started_at))} / {_esc(_when(r.finished_at))}</td></tr></table>
<p>At the verification poses, measured: {_esc(headline)}.</p>
{simulation_html(r.simulation)}
<h2>Measurement plan</h2>{adaptive_html(r.adaptive)}
<h2>Verification errors before and after calibration (cf. paper Table 7)</h2>{_table7_html(r)}
<h2>Machine time: estimated against actual</h2>{time_html(r.machine_time)}
<h2>Links: holds and retries</h2>{links_html(r.links)}
{'' if not r.stations else '<h2>Instrument stations</h2><ul>' + ''.join(
    f'<li>{_esc(line)}</li>' for line in stations_lines(r.stations)) + f'</ul><p>{_esc(r.stations["frames"])}</p>'}
<h2>Absolute position error at the verification poses (cf. paper Fig. 13)</h2>
{img(_per_pose_plot(r, 0, "position", "mm"), "position error per verification pose")}
<h2>Absolute orientation error at the verification poses (cf. paper Fig. 14)</h2>
{img(_per_pose_plot(r, 1, "orientation", "deg"), "orientation error per verification pose")}
<h2>Identified parameters</h2>{img(_parameter_plot(r), "identified parameters per leg")}{_parameters_html(r)}
<h2>Least squares against L-infinity</h2>{img(_comparison_plot(r), "LS against L-infinity")}
<h2>Plausibility of the identified parameters</h2>{plausibility_html(r.plausibility)}
<h2>Physics: what the run's own recording shows beyond the geometry</h2>
{physics_html(_jsonable(r.physics), after_brief, (r.compensation or {}).get("mode") == "offsets_only")}
<h2>What the run prepared for the controller</h2>{compensation_html(_jsonable(r.compensation))}
<h2>Upload</h2>{upload_html(_jsonable(r.upload))}
<h2>Drift since the machine's last calibration</h2>{drift_html(r.drift)}
</body></html>"""


def _when(iso_time: str) -> str:
    """2026-11-27T20:06:56.144147+00:00 as 2026-11-27 20:06:56."""
    return iso_time[:19].replace("T", " ")


__all__ = ["RunReport", "links_lines", "report_html", "report_json", "stations_lines", "write_run_report"]


def write_run_report(out_dir: Path, r: RunReport) -> tuple[Path, Path]:
    """Write report.json and report.html into out_dir (created if needed); return both paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    json_path, html_path = out_dir / "report.json", out_dir / "report.html"
    json_path.write_text(json.dumps(report_json(r), indent=2, allow_nan=False))
    html_path.write_text(report_html(r), encoding="utf-8")
    return json_path, html_path
