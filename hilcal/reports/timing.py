"""Machine time in the run report: the estimate made before any motion against the time each phase took.

Pure: the caller gives the estimate (``hilcal.planning.machine_time.TimeEstimate``), the timing it was made with,
and the actual duration of each phase (seconds from the journal, None when unknown). Actual times are wall
clock, so a pause or an interruption inside a phase counts in it; ``interrupted`` says so.
"""

from __future__ import annotations

import html
from collections.abc import Mapping
from typing import Any

from hilcal.planning.machine_time import TimeEstimate, format_minutes

PHASE_LABELS = {"measure": "measure poses", "verify": "verify poses (before)", "verify_after": "verify poses (after)",
                "acceptance": "ISO 9283 acceptance test", "return_home": "back home"}


def time_section(estimate: TimeEstimate, actual_s: Mapping[str, float | None], timing: Mapping[str, float],
                 *, interrupted: bool = False) -> dict[str, Any]:
    """The report.json ``machine_time`` object: per phase estimated parts and actual seconds, and the totals."""
    phases = {}
    for p in estimate.phases:
        actual = actual_s.get(p.phase)
        phases[p.phase] = {
            "n_poses": p.n_poses, "n_moves": p.n_moves, "leg_travel_mm": p.leg_travel_mm,
            "estimated_s": p.total_s, "estimated_motion_s": p.motion_s, "estimated_settle_s": p.settle_s,
            "estimated_probing_s": p.probing_s, "actual_s": actual,
            "actual_over_estimated": None if actual is None or p.total_s <= 0 else actual / p.total_s,
        }
    known = [p.phase for p in estimate.phases if actual_s.get(p.phase) is not None]
    return {
        "estimated_s": estimate.total_s, "estimated_motion_s": estimate.motion_s,
        "estimated_settle_s": estimate.settle_s, "estimated_probing_s": estimate.probing_s,
        "actual_s": sum(float(actual_s[k]) for k in known) if known else None,
        "actual_phases": known, "interrupted": interrupted, "timing": dict(timing), "phases": phases,
    }


def _cell(seconds: float | None) -> str:
    return "n/a" if seconds is None else f"{seconds:.1f} s ({html.escape(format_minutes(seconds))})"


def time_html(section: Mapping[str, Any] | None) -> str:
    """The report.html table: estimated (motion + settle + probing) against actual, per phase."""
    if not section:
        return "<p>no machine-time estimate was recorded for this run.</p>"
    rows = ""
    for name, p in section["phases"].items():
        ratio = p["actual_over_estimated"]
        label = html.escape(PHASE_LABELS.get(name, name))
        rows += (f"<tr><th>{label}</th><td>{p['n_poses']}</td><td>{p['n_moves']}</td>"
                 f"<td>{p['leg_travel_mm'] / 1000:.2f}</td><td>{p['estimated_motion_s']:.1f}</td>"
                 f"<td>{p['estimated_settle_s']:.1f}</td><td>{p['estimated_probing_s']:.1f}</td>"
                 f"<td>{_cell(p['estimated_s'])}</td><td>{_cell(p['actual_s'])}</td>"
                 f"<td>{'n/a' if ratio is None else f'{ratio:.2f}'}</td></tr>")
    t = section["timing"]
    timing = html.escape(f"legs {t.get('leg_speed_mm_s', 0):g} mm/s and {t.get('leg_accel_mm_s2', 0):g} mm/s², "
                         f"settle {t.get('settle_s', 0):g} s, {t.get('cmm_s_per_pose', 0):g} s to measure a pose, "
                         f"{t.get('move_overhead_s', 0):g} s per move")
    note = (" The run was interrupted or paused: actual times include the stop."
            if section.get("interrupted") else "")
    return (f"<table><tr><th>phase</th><th>poses</th><th>moves</th><th>leg travel (m)</th>"
            f"<th>motion (s)</th><th>settle (s)</th><th>probing (s)</th><th>estimated</th><th>actual</th>"
            f"<th>actual / estimated</th></tr>{rows}<tr><th>total</th><td></td><td></td><td></td>"
            f"<td>{section['estimated_motion_s']:.1f}</td><td>{section['estimated_settle_s']:.1f}</td>"
            f"<td>{section['estimated_probing_s']:.1f}</td><td>{_cell(section['estimated_s'])}</td>"
            f"<td>{_cell(section['actual_s'])}</td><td></td></tr></table>"
            f"<p>Estimated before any motion from the station's timing ({timing}); leg travel is the sum over moves "
            f"of the largest leg-length change. Actual: wall-clock time from the first move of a phase to its last "
            f"measurement (journal).{note}</p>")
