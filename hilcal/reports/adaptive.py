"""The adaptive plan's section of a run report: why the measure phase stopped, what it predicted, what the verification
then measured.

Pure: the caller hands over the measure phase's last decision (its stop reason with the prediction, as
``hilcal.planning.stopping.StopReason.to_json`` gives it), the run's adaptive settings and budget, and the verify-after
maximum measured after the upload. The sentence says only what those show: a held prediction is "measured at or below
the predicted upper bound", never more.
"""

from __future__ import annotations

import html
from collections.abc import Mapping
from typing import Any

from hilcal.planning.machine_time import format_minutes

KIND_TITLES = {"target": "target reached", "converged": "converged (the prediction stopped improving)",
               "budget": "budget reached", "not_identifiable": "not identifiable"}


def _um(mm: float | None) -> str:
    return "not measured" if mm is None else f"{mm * 1000:.1f} µm"


def _min(seconds: float) -> str:
    return format_minutes(seconds)


def adaptive_section(decision: Mapping[str, Any], run: Mapping[str, Any], measured_max_mm: float | None,
                     plans: Mapping[str, str | None], physics: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """report.json's `adaptive`: the stop (kind, sentence, prediction), rows and machine time against the fixed plan,
    and whether the verification stayed within the prediction and the target.

    decision: ``procedures.adaptive.progress`` of the stop; run: ``AdaptiveRun.to_json()``; measured_max_mm: the
    verify-after maximum position error (None when the run did not verify); plans: reference and executed plan hashes;
    physics: the run's physics step ({effects, predicted_max_mm}: what its diagnosis named and the held-out maximum it
    predicted with them), None without one.
    """
    stop = decision["stop"]
    prediction = stop.get("prediction")
    budget = run["budget"]
    target = run["options"].get("target_mm")
    fixed_s = budget["fixed_measure_s"]
    held = None if prediction is None or measured_max_mm is None else measured_max_mm <= prediction["upper_mm"]
    target_met = None if target is None or measured_max_mm is None else measured_max_mm <= target
    section = {
        "kind": stop["kind"], "title": KIND_TITLES.get(stop["kind"], stop["kind"]), "sentence": stop["sentence"],
        "n_rows": stop["n_rows"], "distinct_poses": decision.get("distinct"),
        "measure_time_s": stop["elapsed_s"], "measure_budget_s": budget["measure_s"],
        "run_budget_s": budget["total_s"], "budget_source": budget["source"],
        "fixed_plan": {"measure_rows": budget["fixed_measure_rows"], "measure_s": fixed_s,
                       "total_s": budget["fixed_total_s"]},
        "time_fraction_of_fixed": stop["elapsed_s"] / fixed_s if fixed_s > 0 else None,
        "target_mm": target, "prediction": prediction,
        "verification": {"measured_max_mm": measured_max_mm, "within_prediction": held, "target_met": target_met},
        "unidentifiable": stop.get("unidentifiable", []), "screening": stop.get("screening"),
        "minimum": decision.get("minimum"), "settings": run.get("settings"), "plans": dict(plans),
        "physics": None if physics is None else dict(physics),
    }
    section["summary"] = summary(section)
    return section


def summary(s: Mapping[str, Any]) -> str:
    """The stop in one honest sentence: why, after how much, what was predicted and what was then measured."""
    kind, p, v = s["kind"], s.get("prediction"), s["verification"]
    fraction = s.get("time_fraction_of_fixed")
    cost = (f"after {s['n_rows']} rows ({_min(s['measure_time_s'])} of machine time"
            + ("" if fraction is None else f", {fraction:.2f} x the fixed plan's measure phase") + ")")
    if kind == "not_identifiable":
        return f"Not identifiable {cost}: {s['sentence']}. Nothing was identified or uploaded."
    lead = {"target": f"Target reached {cost}", "converged": f"The prediction stopped improving {cost}",
            "budget": f"Budget reached {cost}: the accuracy proven by then"}.get(kind, f"Stopped ({kind}) {cost}")
    predicted = ("no prediction" if p is None else
                 f"the verify maximum predicted below {_um(p['upper_mm'])} with {p['confidence']:.0%} confidence "
                 f"(median {_um(p['max_mm'])})")
    target = s.get("target_mm")
    if target is not None:
        predicted += f", target {_um(target)}"
    screening, physics = s.get("screening") or {}, s.get("physics") or {}
    if screening.get("suspected"):  # the bound is the geometric model's: its residuals hold the missing physics
        predicted += ("; the screening found signs of missing physics, so this bound is the geometric model's and the "
                      "rows went on for the diagnosis")
        if physics.get("effects"):
            predicted += (f"; the run's diagnosis named {', '.join(physics['effects'])}, and with them predicted "
                          f"{_um(physics.get('predicted_max_mm'))} on the held-out verify poses")
    if v["measured_max_mm"] is None:
        return f"{lead}: {predicted}; the verification after the upload was not measured."
    held = {True: "at or below the predicted bound", False: "ABOVE the predicted bound"}.get(v["within_prediction"],
                                                                                             "no bound to compare")
    met = "" if v["target_met"] is None else ("; the target is met" if v["target_met"] else "; the target is NOT met")
    return f"{lead}: {predicted}; the verification after the upload measured {_um(v['measured_max_mm'])}: {held}{met}."


def adaptive_html(section: Mapping[str, Any] | None) -> str:
    """The report page's part: the summary, the prediction against the measurement, and the budget."""
    if not section:
        return "<p>Fixed plan: every measure pose of the plan was measured.</p>"
    e = html.escape
    p = section.get("prediction") or {}
    fixed = section["fixed_plan"]
    rows = [("stop", e(section["title"])), ("why", e(section["sentence"])),
            ("rows measured", f"{section['n_rows']} ({section.get('distinct_poses')} distinct poses); the fixed plan: "
                              f"{fixed['measure_rows']}"),
            ("measure phase, machine time (estimate)", f"{_min(section['measure_time_s'])} of a budget of "
             f"{_min(section['measure_budget_s'])}; the fixed plan: {_min(fixed['measure_s'])}"),
            ("whole run's budget", f"{_min(section['run_budget_s'])} ({e(section['budget_source'])})")]
    if p:
        rows.append(("predicted verify maximum", f"median {_um(p['max_mm'])}, 5-95 %: {_um(p['low_mm'])} to "
                     f"{_um(p['upper_mm'])}; noise {e(p.get('noise_source') or '')}"))
    rows.append(("measured verify maximum (after the upload)", _um(section["verification"]["measured_max_mm"])))
    table = "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows)
    return f"<p><b>{e(section['summary'])}</b></p><table class=\"kv\">{table}</table>"
