"""Statistics of the diagnosis study: naming rates, held-out gains, after/floor, false alarms with exact CIs."""

from __future__ import annotations

import statistics
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.stats import binomtest

from sim_devices.rig.config import EFFECT_NAMES

RATIO_TARGET = 1.5
FALSE_ALARM_TARGET = 0.05
PAIR_TARGET = 0.90
UNLISTED_TARGET = 0.90
GAIN_TARGET = 0.5
"""The generic model must at least halve the geometry-only held-out verify RMS."""


def clopper_pearson(k: int, n: int) -> tuple[float, float]:
    if n == 0:
        return float("nan"), float("nan")
    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="exact")
    return float(ci.low), float(ci.high)


def median(values: Sequence[float]) -> float:
    v = [x for x in values if x is not None and np.isfinite(x)]
    return statistics.median(v) if v else float("nan")


def maximum(values: Sequence[float]) -> float:
    v = [x for x in values if x is not None and np.isfinite(x)]
    return max(v) if v else float("nan")


def _rate(k: int, n: int) -> dict[str, Any]:
    lo, hi = clopper_pearson(k, n)
    return {"k": k, "n": n, "rate": k / n if n else float("nan"), "ci": (lo, hi)}


def singles(results: list[dict[str, Any]]) -> dict[tuple[str, float, bool], dict[str, Any]]:
    """Per (effect, scale, bare): named first, named alone (no other physics), after/floor of the named runs."""
    out = {}
    runs = [r for r in results if r["kind"] == "single"]
    for key in sorted({(r["effects"][0], r["scale"], r["bare"]) for r in runs}):
        cell = [r for r in runs if (r["effects"][0], r["scale"], r["bare"]) == key]
        hits = [r for r in cell if r["effect"] == key[0]]
        ratios = [r["after_mm"] / r["floor_mm"] for r in hits]
        out[key] = {
            **_rate(len(hits), len(cell)),
            "clean": sum(1 for r in hits if not r["false_library"] and not r["unexplained"]),
            "ratio_median": median(ratios), "ratio_max": maximum(ratios),
            "over": sum(1 for x in ratios if x > RATIO_TARGET),
            "before_floor": median([r["before_mm"] / r["floor_mm"] for r in cell]),
        }
    return out


def pairs(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Both effects of a pair named; extras; after/floor where both are named."""
    runs = [r for r in results if r["kind"] == "pair"]
    table = {}
    for key in sorted({tuple(r["effects"]) for r in runs}):
        cell = [r for r in runs if tuple(r["effects"]) == key]
        both = [r for r in cell if set(key) <= set(r["named"])]
        ratios = [r["after_mm"] / r["floor_mm"] for r in both]
        table[key] = {**_rate(len(both), len(cell)), "extra": sum(1 for r in both if r["false_library"]),
                      "ratio_median": median(ratios), "ratio_max": maximum(ratios),
                      "over": sum(1 for x in ratios if x > RATIO_TARGET)}
    both_all = [r for r in runs if set(r["effects"]) <= set(r["named"])]
    ratios = [r["after_mm"] / r["floor_mm"] for r in both_all]
    return {"table": table, "total": _rate(len(both_all), len(runs)), "ratio_median": median(ratios),
            "ratio_max": maximum(ratios), "over": sum(1 for x in ratios if x > RATIO_TARGET),
            "extra": sum(1 for r in both_all if r["false_library"])}


def unlisted(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Out-of-library effects (alone or with library physics): unexplained, held-out gain, no 'within noise'."""
    out: dict[str, Any] = {}
    for kind in ("unlisted", "combo"):
        runs = [r for r in results if r["kind"] == kind]
        table = {}
        for key in sorted({(tuple(r["effects"]), r["scale"]) for r in runs}):
            cell = [r for r in runs if (tuple(r["effects"]), r["scale"]) == key]
            said = [r for r in cell if r["unexplained"]]
            gains = [r["after_mm"] / r["before_mm"] for r in cell]
            library_truth = [e for e in key[0] if e in EFFECT_NAMES]
            table[key] = {
                **_rate(len(said), len(cell)),
                "first": sum(1 for r in cell if r["effect"] == "unexplained"),
                "library_named": sum(1 for r in cell if r["false_library"]),
                "library_found": sum(1 for r in cell if set(library_truth) <= set(r["library_named"])),
                "gain_median": median(gains), "gain_max": maximum(gains),
                "halved": sum(1 for g in gains if g <= GAIN_TARGET),
                "within_claims": sum(1 for r in cell if r["within_claim"]),
                "before_floor": median([r["before_mm"] / r["floor_mm"] for r in cell]),
                "after_floor": median([r["after_mm"] / r["floor_mm"] for r in cell]),
                "pinned": sum(1 for r in cell for s in r["shapes"] if s["pinned"]),
                "shapes": sum(len(r["shapes"]) for r in cell),
            }
        out[kind] = table
    return out


def nulls(results: list[dict[str, Any]]) -> dict[str, Any]:
    """False alarms (anything but 'none') per noise model and for recordings without cmd/temp_c."""
    runs = [r for r in results if r["kind"] == "null"]
    groups = {m: [r for r in runs if r["noise_model"] == m and not r["bare"]]
              for m in sorted({r["noise_model"] for r in runs})}
    groups["without cmd and temp_c"] = [r for r in runs if r["bare"]]
    groups["pooled"] = runs
    out = {}
    for name, cell in groups.items():
        alarms = [r for r in cell if r["named"]]
        out[name] = {**_rate(len(alarms), len(cell)),
                     "which": sorted({e for r in alarms for e in r["named"]}),
                     "within_claims": sum(1 for r in cell if r["within_claim"]),
                     "ratio_median": median([r["ratio_final"] for r in cell])}
    return out


def outliers(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Planted gross errors excluded exactly (no more, no fewer) with the effect still named first; and recordings
    without planted errors that lost a row to the screen (false exclusions), nulls among them."""
    planted = [r for r in results if r["kind"] == "outlier"]
    exact = [r for r in planted if r["outliers_excluded"] == r["outliers_planted"]]
    named = [r for r in exact if r["effect"] == r["effects"][0]]
    clean = [r for r in results if r["kind"] != "outlier"]
    null_rows = [r for r in clean if r["kind"] == "null"]
    return {"exact": _rate(len(exact), len(planted)), "named": _rate(len(named), len(planted)),
            "ratio_median": median([r["after_mm"] / r["floor_mm"] for r in named]),
            "false": _rate(sum(1 for r in clean if r["outliers_excluded"]), len(clean)),
            "false_nulls": _rate(sum(1 for r in null_rows if r["outliers_excluded"]), len(null_rows))}


def summarize(results: list[dict[str, Any]]) -> dict[str, Any]:
    seconds = [r["seconds"] for r in results]
    return {
        "singles": singles(results), "pairs": pairs(results), "unlisted": unlisted(results), "nulls": nulls(results),
        "outliers": outliers(results),
        "range_violations": sum(1 for r in results if not r["in_range"]),
        "seconds_median": median(seconds), "seconds_max": maximum(seconds), "n_runs": len(results),
    }
