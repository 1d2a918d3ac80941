"""The diagnosis study's "set-up faults and aliases" part: scale faults of 2-10 % on one or two legs of a light
hexapod, with and without a near-alias compliance, declared hydraulic (linear transducers) or electric (motor
encoders), and the issue's own case (electric, one leg's mm/rev 4-8 % off, with the alias) over more seeds.

A case passes when: `sensor_scale` is the first effect; it is graded a fault on exactly the faulty legs; each
faulty leg's value is within 10 % of the truth; no hydraulic effect is named on electric legs; nothing impossible
is named; and, with the alias, the answer names the alias or reports it as a near-alias with what separates it.
"""

from __future__ import annotations

import time
from typing import Any

from diagnosis_cases import ALPHA, FaultCase, build_fault_case, fault_alias_cases, init_worker
from diagnosis_summary import clopper_pearson, median

from hilcal.discovery.search import diagnose
from hilcal.metrics import AccuracySummary

VALUE_TOLERANCE = 0.10
DONE_WHEN_PCT = (4.0, 8.0)


def study_cases(grid_seeds: int, done_when_seeds: int) -> list[FaultCase]:
    """The grid (both kinds x one or two legs x alias or not) and the issue's own case over more seeds."""
    return fault_alias_cases(range(grid_seeds)) + [
        FaultCase("electric", 1, True, 1000 + seed, fault_pct=DONE_WHEN_PCT) for seed in range(done_when_seeds)]


def run_fault_case(case: FaultCase, n_boot: int) -> dict[str, Any]:
    """Build, diagnose and score one set-up-fault case."""
    init_worker()
    built = build_fault_case(case)
    rec, robot, truth = built.recording, built.robot, built.truth
    t0 = time.perf_counter()
    diag = diagnose(rec, robot, alpha=ALPHA, n_boot=n_boot, seed=case.seed)
    elapsed = time.perf_counter() - t0
    scale = next((n for n in diag.named if n.effect == "sensor_scale"), None)
    fault_legs = tuple(sorted(scale.legs)) if scale is not None and scale.grade == "fault" else ()
    errors = [abs(diag.parameters.get(f"leg{leg}_sensor_scale_ppm", 0.0) / ppm - 1.0)
              for leg, ppm in zip(truth.fault_legs, truth.fault_ppm, strict=True)]
    alias_named = truth.alias_effect is not None and truth.alias_effect in diag.effects
    alias_reported = truth.alias_effect is not None and any(
        a.other == truth.alias_effect and (a.correlation_now <= 0.8 or a.separating_poses is not None)
        for a in diag.aliases)
    impossible = any(r.grade == "impossible" for r in diag.parameter_table)
    verify = rec.phase == "verify"
    ok = (diag.effect == "sensor_scale" and fault_legs == tuple(truth.fault_legs)
          and max(errors) <= VALUE_TOLERANCE and not set(diag.effects) & set(truth.not_physical) and not impossible
          and (truth.alias_effect is None or alias_named or alias_reported))
    return {
        "kind": "fault", "actuators": case.actuators, "n_fault_legs": case.n_fault_legs, "alias": case.alias,
        "seed": case.seed, "done_when": case.fault_pct == DONE_WHEN_PCT,
        "fault_pct": [abs(v) / 1e4 for v in truth.fault_ppm], "effect": diag.effect, "named": list(diag.effects),
        "fault_legs_found": list(fault_legs), "fault_legs_true": list(truth.fault_legs),
        "max_value_error": max(errors), "hydraulic_on_electric": sorted(set(diag.effects) & set(truth.not_physical)),
        "impossible_named": impossible, "alias_named": alias_named, "alias_reported": alias_reported,
        "before_mm": diag.before.position_mm.rms, "after_mm": diag.after.position_mm.rms,
        "floor_mm": AccuracySummary.of(rec.meas[verify], built.true_poses[verify]).position_mm.rms,
        "after_unshifted_mm": (diag.after.position_mm.rms if diag.session_shift is None
                               or diag.session_shift.verify_without_shift is None
                               else diag.session_shift.verify_without_shift.position_mm.rms),
        "not_converged": list(diag.not_converged), "ok": ok, "seconds": elapsed,
    }


def summarize_faults(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Pass rates per cell and for the issue's own case, with Clopper-Pearson intervals."""
    cells: dict[tuple[str, int, bool], list[dict[str, Any]]] = {}
    for r in results:
        if not r["done_when"]:
            cells.setdefault((r["actuators"], r["n_fault_legs"], r["alias"]), []).append(r)

    def rate(rows: list[dict[str, Any]]) -> dict[str, Any]:
        k, n = sum(r["ok"] for r in rows), len(rows)
        lo, hi = clopper_pearson(k, n)
        return {"k": k, "n": n, "rate": k / n if n else float("nan"), "ci": (lo, hi),
                "median_value_error": median([r["max_value_error"] for r in rows]),
                "median_after_over_floor": median([r["after_mm"] / r["floor_mm"] for r in rows]),
                "median_unshifted_over_floor": median([r["after_unshifted_mm"] / r["floor_mm"] for r in rows])}

    done = [r for r in results if r["done_when"]]
    return {
        "cells": {f"{a}, {n} leg(s), {'with' if al else 'without'} alias": rate(rows)
                  for (a, n, al), rows in sorted(cells.items())},
        "done_when": rate(done) if done else None,
        "hydraulic_on_electric": sum(bool(r["hydraulic_on_electric"]) for r in results),
        "impossible_named": sum(r["impossible_named"] for r in results),
        "failures": [{k: r[k] for k in ("actuators", "n_fault_legs", "alias", "seed", "effect", "named",
                                        "fault_legs_found", "fault_legs_true", "max_value_error")}
                     for r in results if not r["ok"]][:10],
        "n": len(results),
        "median_seconds": median([r["seconds"] for r in results]),
    }


def fault_section(summary: dict[str, Any]) -> list[str]:
    """The doc section of this part."""
    def pct(d: dict[str, Any]) -> str:
        return f"{d['k']}/{d['n']} = {d['rate']:.0%} (95% CI {d['ci'][0]:.0%}-{d['ci'][1]:.0%})"

    lines = ["## Set-up faults and aliases\n", " ".join([
        "A light electric hexapod (examples/electric_hexapod, 4 kg) with a scale fault of 2-10 % of the reported",
        "stroke on one or two legs (motor encoders with a mis-set mm/rev; declared hydraulic, linear transducers with",
        "a mis-set gradient), with and without a near-alias compliance (a slack drive, or a soft oil column), 2 x 54",
        "measure rows in two sessions and 60 verify rows in a third, no commanded poses, no temperature",
        "(`benchmarks/studies/diagnosis_cases.py`: `build_fault_case`). A case passes when `sensor_scale` is the",
        "first effect, graded a fault on exactly the faulty legs, each within 10 % of the truth, no hydraulic effect",
        "is named on electric legs, nothing impossible is named, and the alias (when present) is named or reported",
        "as a near-alias with what separates it.\n"])]
    if summary["done_when"] is not None:
        d = summary["done_when"]
        lines.append(f"- The issue's case (electric, one leg's mm/rev 4-8 % off, with the alias): passes in {pct(d)} "
                     f"(target >= 90%: {'met' if d['rate'] >= 0.9 else '**not met**'}); median value error "
                     f"{d['median_value_error']:.2%}.")
    lines.append(f"- Hydraulic effects named on electric legs: {summary['hydraulic_on_electric']} (target 0); "
                 f"impossible values named: {summary['impossible_named']} (target 0).")
    lines += ["", "| case | passes | median value error | median after / floor | same, held-out zero shift removed |",
              "|---|---|---|---|---|"]
    for name, d in summary["cells"].items():
        lines.append(f"| {name} | {pct(d)} | {d['median_value_error']:.2%} | {d['median_after_over_floor']:.2f} | "
                     f"{d['median_unshifted_over_floor']:.2f} |")
    lines += ["", " ".join([
        "After / floor: held-out RMS position error of the final model over that of the measured against the true",
        "pose. The electric machine is re-homed at each power-on, so its verify rows (a third session) start from",
        "leg zeros that moved by a few µm (N(0, (3 µm)^2) per leg): no model fitted on the other sessions can",
        "predict that, and the diagnosis reports it as a zero shift in the held-out rows instead of fitting them.",
        "The last column removes the shift that the diagnosis estimated on the verify rows (`session_shift`).",
        "The declared-hydraulic cases have no re-homing."])]
    if summary["failures"]:
        lines += ["", "Failed cases (first 10): " + "; ".join(
            f"{f['actuators']} {f['n_fault_legs']} leg(s) {'alias' if f['alias'] else 'no alias'} seed {f['seed']}: "
            f"effects {', '.join(f['named']) or 'none'}, fault legs found {f['fault_legs_found']} "
            f"(true {f['fault_legs_true']}), value error {f['max_value_error']:.1%}" for f in summary["failures"])]
    return [*lines, ""]


def verdict_line(summary: dict[str, Any]) -> str:
    d = summary["done_when"]
    if d is None:
        return ""
    cells = list(summary["cells"].values())
    k, n = sum(c["k"] for c in cells), sum(c["n"] for c in cells)
    return (f"- Set-up faults: electric, one leg's mm/rev 4-8 % off with a near-alias compliance: named as a "
            f"`sensor_scale` fault on the right leg within 10 % in {d['k']}/{d['n']} = {d['rate']:.0%} (target >= 90%: "
            f"{'met' if d['rate'] >= 0.9 else '**not met**'}); the whole 2-10 % grid {k}/{n}; hydraulic effects on "
            f"electric legs: {summary['hydraulic_on_electric']} (target 0).")

