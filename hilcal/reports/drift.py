"""The drift section of a run report and of the panel: what moved since the machine's last calibration, the
flags in plain sentences, and trend plots per parameter (value ± standard error against time, with the step).

Takes ``hilcal.drift.DriftResult.to_json()`` (what report.json stores), so the panel can draw the same plots from
the records without recomputing anything here.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from datetime import datetime
from typing import Any

from hilcal.drift import describe
from hilcal.reports.figures import fixed_margins, new_figure, png_base64

MAX_PANELS = 12


def trend_names(drift: dict[str, Any], limit: int = MAX_PANELS) -> list[str]:
    """The parameters worth a plot: flagged ones first, then the legs' strokes at home (what the data pin down)."""
    params = drift.get("parameters") or []
    flagged = [p["name"] for p in params if p.get("flag") or p.get("since_last_flagged")]
    strokes = [p["name"] for p in params if p["name"].endswith("_stroke_at_home_mm") and p["name"] not in flagged]
    return (flagged + strokes)[:limit]


def trend_png(drift: dict[str, Any], names: Sequence[str] | None = None) -> str | None:
    """Trend plots (PNG, base64) of the named parameters: value - first value (mm) ± σ against the date."""
    by_name = {p["name"]: p for p in drift.get("parameters") or []}
    names = [n for n in (names if names is not None else trend_names(drift)) if n in by_name]
    if not names or drift.get("n_calibrations", 0) < 2:
        return None
    cols = min(3, len(names))
    rows = math.ceil(len(names) / cols)
    fig = new_figure(4.2 * cols, 2.6 * rows)
    threshold = float(drift.get("threshold_mm") or 0.0)
    for k, name in enumerate(names):
        p = by_name[name]
        ax = fig.add_subplot(rows, cols, k + 1)
        dates = [datetime.fromisoformat(t) for t in p["times"]]
        first = p["values_mm"][0]
        values = [v - first for v in p["values_mm"]]
        ax.errorbar(dates, values, yerr=p["std_mm"], fmt="o", ms=3, color="tab:blue", ecolor="0.6", capsize=2)
        k_step = p.get("step_index")
        if p.get("flag") == "step" and k_step:
            before = sum(values[:k_step]) / k_step
            ax.plot(dates[:k_step], [before] * k_step, color="tab:red", lw=1.5)
            ax.plot(dates[k_step:], [before + p["step_mm"]] * (len(values) - k_step), color="tab:red", lw=1.5)
        ax.axhspan(-threshold, threshold, color="0.92", zorder=0)
        label = describe(name)[0]
        ax.set_title(label + (" (flagged)" if p.get("flag") or p.get("since_last_flagged") else ""), fontsize=9,
                     color="tab:red" if p.get("flag") or p.get("since_last_flagged") else "black")
        ax.set_ylabel("change (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
        for tick in ax.get_xticklabels():
            tick.set_rotation(30)
    fixed_margins(fig, left_in=0.75, right_in=0.15, bottom_in=0.7, top_in=0.3, wspace_in=0.8, hspace_in=0.85)
    return png_base64(fig, dpi=90)


def _esc(value: object) -> str:
    return html.escape(str(value))


def drift_html(drift: dict[str, Any] | None) -> str:
    """The report's drift section: since the last calibration, flags over the history, trend plots."""
    if not drift:
        return "<p>no drift: the run identified no parameters, or no records were available</p>"
    if drift.get("error"):
        return f"<p>{_esc(drift['error'])}</p>"
    n = drift.get("n_calibrations", 0)
    head = (f"<p>machine <b>{_esc(drift.get('machine'))}</b>: {n} calibration(s) with this one. "
            f"Rule: {_esc(drift.get('rule', ''))}.</p>")
    if n < 2:
        return head + "<p>this is the machine's first recorded calibration: nothing to compare yet</p>"
    since = drift.get("since_last") or []
    flags = drift.get("flags") or []
    parts = [head,
             "<p><b>since the last calibration:</b> " + ("; ".join(_esc(s) for s in since) if since else
                                                          "no parameter moved beyond the rule") + "</p>",
             "<p><b>over the history:</b></p><ul>" + ("".join(f"<li>{_esc(f)}</li>" for f in flags) if flags else
                                                       "<li>nothing flagged</li>") + "</ul>"]
    png = trend_png(drift)
    if png:
        parts.append(f'<img alt="parameter trends" src="data:image/png;base64,{png}">')
    rows = "".join(
        f"<tr><td>{_esc(describe(p['name'])[0])}</td><td>{_num(p.get('since_last_mm'))}</td>"
        f"<td>{_num(p.get('since_last_sigma'), 1)}</td><td>{_num(p.get('step_mm'))}</td>"
        f"<td>{_num(p.get('step_sigma'), 1)}</td><td>{_esc(p.get('flag') or '')}</td></tr>"
        for p in drift.get("parameters") or [] if p["name"].endswith(("_stroke_at_home_mm", "_l0_mm"))
        or p.get("flag"))
    parts.append("<table><tr><th>parameter</th><th>since last (mm)</th><th>σ</th><th>best step (mm)</th>"
                 f"<th>σ</th><th>flag</th></tr>{rows}</table>")
    return "".join(parts)


def _num(value: float | None, digits: int = 4) -> str:
    return "-" if value is None else f"{value:+.{digits}f}"
