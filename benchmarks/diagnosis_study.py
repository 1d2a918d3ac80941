"""Power and false-alarm study of `hilcal.diagnosis.diagnose` on seeded concealed-effect recordings.

Why: the diagnosis names one missing physical effect (or "none" / "unexplained") from a calibration recording.
Before trusting it on the shop floor we need to know how often it names the right effect, how small an effect it
can see, what the refit buys on held-out poses compared with the best achievable (measurement noise only), and
how often it cries wolf on a rig without any missing physics. The simulated rig (`sim_devices`) conceals one
effect at a time with seeded, realistic magnitudes (`concealed_effect_config`); its true poses are used here
for scoring only, never by the diagnosis.

Run ``python benchmarks/diagnosis_study.py [--quick] [--jobs N]``; it writes docs/diagnosis_study.md and
docs/img/diagnosis_*.png. Every run is seeded, so the output is deterministic (up to the date and runtime).
"""

from __future__ import annotations

import argparse
import logging
import multiprocessing
import os
import platform
import statistics
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
import structlog
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from scipy.stats import binomtest

from hilcal.design import factorial_exchange, verification_poses
from hilcal.diagnosis import N_GEO, diagnose
from hilcal.error_models import implicit_residuals
from hilcal.kinematics import Geometry, forward_kinematics
from hilcal.metrics import AccuracySummary
from hilcal.physics import CANDIDATES_BY_NAME
from hilcal.robot import Robot, default_robot
from procedures.simulated_recording import simulate_with_truth
from sim_devices.config import (
    EFFECT_NAMES,
    EffectsConfig,
    RigConfig,
    concealed_effect_config,
    load_errors,
    random_errors,
)

ROOT = Path(__file__).resolve().parents[1]
DOC_PATH = ROOT / "docs" / "diagnosis_study.md"
IMG_DIR = ROOT / "docs" / "img"

EFFECTS: tuple[str, ...] = tuple(EFFECT_NAMES)
OUTCOMES: tuple[str, ...] = ("none", "unexplained", *EFFECTS)
NOISE_MODELS = ("gaussian", "distance", "student_t")
SHORT = {
    "none": "none",
    "unexplained": "unexpl.",
    "leg_compliance": "compliance",
    "sensor_scale": "scale",
    "thermal_expansion": "thermal",
    "joint_backlash": "backlash",
    "oil_column_compliance": "oil column",
}

N_MEASURE = 32
N_VERIFY = 24
VERIFY_SEED = 0
NULL_GEOMETRY_SIGMA_MM = 0.5
NULL_SEED_OFFSET = 10_000
"""Null recordings use rig seeds NULL_SEED_OFFSET + k, so their noise, CMM placement and errors are fresh."""

DETECTION_TARGET = 0.80
RATIO_TARGET = 1.5
FALSE_ALARM_TARGET = 0.05
ALPHA = 0.05


@dataclass(frozen=True)
class StudyPlan:
    quick: bool
    scales: tuple[float, ...]
    effect_seeds: int
    null_seeds: int
    n_boot: int


FULL_PLAN = StudyPlan(quick=False, scales=(0.25, 0.5, 1.0, 2.0), effect_seeds=16, null_seeds=200, n_boot=1999)
QUICK_PLAN = StudyPlan(quick=True, scales=(0.5, 1.0, 2.0), effect_seeds=3, null_seeds=10, n_boot=999)


@dataclass(frozen=True)
class Case:
    """One simulated recording and its diagnosis."""

    effect: str
    """The concealed truth ('none' for a null recording)."""
    scale: float
    seed: int
    noise_model: str
    example: bool = False
    """Also return the per-leg residuals before/after (for the example plot)."""
    temp_sensor_noise_k: float | None = None
    """Override the temperature sensor noise (ablation); None keeps the rig's default (0.05 K)."""


# ---------------------------------------------------------------------------------------------- worker

_WORKER: dict[str, Any] = {}


def _init_worker(measure_poses: np.ndarray, verify_poses: np.ndarray) -> None:
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    robot = default_robot()
    _WORKER.update(
        robot=robot, measure=measure_poses, verify=verify_poses, table2=load_errors("table2", robot)
    )


def run_case(case: Case, n_boot: int) -> dict[str, Any]:
    """Simulate, diagnose and score one recording (the truth is used for scoring only)."""
    robot: Robot = _WORKER["robot"]
    if case.effect == "none":
        errors = random_errors(case.seed, NULL_GEOMETRY_SIGMA_MM)
        effects = EffectsConfig()
    else:
        errors = _WORKER["table2"]
        effects = concealed_effect_config(case.effect, case.scale, case.seed)
    config = RigConfig(seed=case.seed, errors=errors, effects=effects, cmm_noise_model=case.noise_model)
    if case.temp_sensor_noise_k is not None:
        temperature = config.temperature.model_copy(update={"sensor_noise_k": case.temp_sensor_noise_k})
        config = config.model_copy(update={"temperature": temperature})
    rec, truth = simulate_with_truth(robot, config, _WORKER["measure"], _WORKER["verify"])
    diag = diagnose(rec, robot, alpha=ALPHA, n_boot=n_boot, seed=case.seed)

    verify = rec.phase == "verify"
    floor = AccuracySummary.of(rec.meas[verify], truth[verify]).position_mm.rms
    signature_um = float("nan")
    if case.effect != "none":
        # The pose a rigid rig (same errors, effect off) takes at the same reported lengths; equals
        # SimulatedRig(..., effects off).true_poses_for_lengths(rec.legs_mm) to 1e-12, ~100x faster.
        rigid_truth = forward_kinematics(Geometry.nominal(robot).perturbed(errors.to_vector()), rec.legs_mm, truth)
        shift = np.linalg.norm(truth[:, :3] - rigid_truth[:, :3], axis=1)
        signature_um = 1000.0 * float(np.sqrt(np.mean(shift**2)))
    out: dict[str, Any] = {
        "effect": case.effect,
        "scale": case.scale,
        "seed": case.seed,
        "noise_model": case.noise_model,
        "ablation": case.temp_sensor_noise_k is not None,
        "named": diag.effect,
        "ambiguous_with": list(diag.ambiguous_with),
        "significant": [t.name for t in diag.tests if t.significant],
        "before_mm": diag.before.position_mm.rms,
        "after_mm": diag.after.position_mm.rms,
        "floor_mm": floor,
        "cv0": diag.cv_rms_geometry_mm,
        "cv1": diag.cv_rms_effect_mm,
        "signature_um": signature_um,
        "n_measure": int(np.sum(~verify)),
    }
    if case.example:
        before = diag.leg_residuals_mm
        after = before
        if diag.effect_fit is not None:
            phi = CANDIDATES_BY_NAME[diag.effect].regressor(diag.context)
            fit = diag.effect_fit
            after = implicit_residuals(fit.geometry(robot), rec.legs_mm + phi @ fit.x[N_GEO:], rec.meas)
        out["example"] = {"before_mm": before, "after_mm": after}
    return out


# ---------------------------------------------------------------------------------------------- study


def _cases(plan: StudyPlan) -> list[Case]:
    cases = [
        Case(effect, scale, seed, "gaussian", example=(seed == 0 and scale == 1.0))
        for effect in EFFECTS
        for scale in plan.scales
        for seed in range(plan.effect_seeds)
    ]
    cases += [
        Case("none", 0.0, NULL_SEED_OFFSET + k, model) for model in NOISE_MODELS for k in range(plan.null_seeds)
    ]
    # Ablation: the thermal refit reads a noisy temperature sensor; the same runs with a perfect sensor show
    # how much of its after/floor excess that noise explains.
    cases += [
        Case("thermal_expansion", max(plan.scales), seed, "gaussian", temp_sensor_noise_k=0.0)
        for seed in range(plan.effect_seeds)
    ]
    return cases


def simulate_all(
    robot: Robot, plan: StudyPlan, jobs: int, progress: Progress | None
) -> tuple[list[dict[str, Any]], np.ndarray]:
    """Every case of the plan, in plan order (independent of the worker count)."""
    measure = factorial_exchange(robot, N_MEASURE, np.random.default_rng(0)).poses
    verify = verification_poses(robot, N_VERIFY, VERIFY_SEED)
    cases = _cases(plan)
    results: list[dict[str, Any] | None] = [None] * len(cases)
    task = progress.add_task("simulate + diagnose recordings", total=len(cases)) if progress else None
    # Longest jobs (thermal, large effects) first for load balance; single-threaded BLAS per worker process.
    order = sorted(range(len(cases)), key=lambda i: (cases[i].effect == "none", -cases[i].scale, i))
    if jobs <= 1:
        _init_worker(measure, verify)
        for i in order:
            results[i] = run_case(cases[i], plan.n_boot)
            if progress is not None and task is not None:
                progress.advance(task)
    else:
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = "1"
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(jobs, mp_context=ctx, initializer=_init_worker, initargs=(measure, verify)) as ex:
            futures = {ex.submit(run_case, cases[i], plan.n_boot): i for i in order}
            for fut in as_completed(futures):
                results[futures[fut]] = fut.result()
                if progress is not None and task is not None:
                    progress.advance(task)
    return [r for r in results if r is not None], measure


# ---------------------------------------------------------------------------------------------- statistics


def clopper_pearson(k: int, n: int) -> tuple[float, float]:
    if n == 0:
        return float("nan"), float("nan")
    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="exact")
    return float(ci.low), float(ci.high)


def _median(values: Sequence[float]) -> float:
    v = [x for x in values if np.isfinite(x)]
    return statistics.median(v) if v else float("nan")


def _max(values: Sequence[float]) -> float:
    v = [x for x in values if np.isfinite(x)]
    return max(v) if v else float("nan")


def summarize(results: list[dict[str, Any]], plan: StudyPlan) -> dict[str, Any]:
    effect_runs = [r for r in results if r["effect"] != "none" and not r["ablation"]]
    null_runs = [r for r in results if r["effect"] == "none"]
    ablation_runs = [r for r in results if r["ablation"]]

    detection: dict[str, dict[float, dict[str, Any]]] = {}
    smallest: dict[str, float | None] = {}
    for effect in EFFECTS:
        detection[effect] = {}
        for scale in plan.scales:
            runs = [r for r in effect_runs if r["effect"] == effect and r["scale"] == scale]
            hits = [r for r in runs if r["named"] == effect]
            ratios = [r["after_mm"] / r["floor_mm"] for r in hits]
            detection[effect][scale] = {
                "n": len(runs),
                "hits": len(hits),
                "rate": len(hits) / len(runs) if runs else float("nan"),
                "ambiguous": sum(1 for r in hits if r["ambiguous_with"]),
                "signature_um": _median([r["signature_um"] for r in runs]),
                "before_um": _median([1000 * r["before_mm"] for r in hits]),
                "after_um": _median([1000 * r["after_mm"] for r in hits]),
                "floor_um": _median([1000 * r["floor_mm"] for r in hits]),
                "ratio_median": _median(ratios),
                "ratio_max": _max(ratios),
                "ratio_over_target": sum(1 for x in ratios if x > RATIO_TARGET),
                "before_ratio_median": _median([r["before_mm"] / r["floor_mm"] for r in runs]),
                "all_ratio_max": _max([r["after_mm"] / r["floor_mm"] for r in runs]),
                "cv_gain_pct": _median([100 * (1 - r["cv1"] / r["cv0"]) for r in hits if r["cv1"] is not None]),
                "ratios": ratios,
            }
        # Smallest tested scale from which this and every larger tested scale reach the target.
        smallest[effect] = None
        for scale in sorted(plan.scales, reverse=True):
            if detection[effect][scale]["rate"] < DETECTION_TARGET:
                break
            smallest[effect] = scale

    confusion_scale = 1.0 if 1.0 in plan.scales else plan.scales[len(plan.scales) // 2]
    at_scale = [r for r in effect_runs if r["scale"] == confusion_scale]
    confusion = {
        effect: {o: sum(1 for r in at_scale if r["effect"] == effect and r["named"] == o) for o in OUTCOMES}
        for effect in EFFECTS
    }

    false_alarms: dict[str, dict[str, Any]] = {}
    for model in [*NOISE_MODELS, "all"]:
        runs = [r for r in null_runs if model == "all" or r["noise_model"] == model]
        named = [r for r in runs if r["named"] in EFFECTS]
        unexplained = [r for r in runs if r["named"] == "unexplained"]
        k = len(named) + len(unexplained)
        lo, hi = clopper_pearson(k, len(runs))
        false_alarms[model] = {
            "n": len(runs),
            "named": len(named),
            "unexplained": len(unexplained),
            "k": k,
            "rate": k / len(runs) if runs else float("nan"),
            "ci": (lo, hi),
            "which": sorted({r["named"] for r in named} | ({"unexplained"} if unexplained else set())),
            "floor_um": _median([1000 * r["floor_mm"] for r in runs]),
            "before_um": _median([1000 * r["before_mm"] for r in runs]),
        }

    top = max(plan.scales)
    thermal_top = [r for r in effect_runs if r["effect"] == "thermal_expansion" and r["scale"] == top]
    ablation = {
        "scale": top,
        "noisy": [r["after_mm"] / r["floor_mm"] for r in thermal_top if r["named"] == r["effect"]],
        "perfect": [r["after_mm"] / r["floor_mm"] for r in ablation_runs if r["named"] == r["effect"]],
        "perfect_hits": sum(1 for r in ablation_runs if r["named"] == r["effect"]),
        "n": len(ablation_runs),
    }
    hits_all = [r for r in effect_runs if r["named"] == r["effect"]]
    all_ratios = [r["after_mm"] / r["floor_mm"] for r in hits_all]
    return {
        "detection": detection,
        "smallest_detectable": smallest,
        "confusion_scale": confusion_scale,
        "confusion": confusion,
        "false_alarms": false_alarms,
        "thermal_sensor_ablation": ablation,
        "ratio_median": _median(all_ratios),
        "ratio_max": _max(all_ratios),
        "ratio_over_target": sum(1 for x in all_ratios if x > RATIO_TARGET),
        "n_hits": len(hits_all),
        "n_effect_runs": len(effect_runs),
        "n_null_runs": len(null_runs),
    }


# ---------------------------------------------------------------------------------------------- plots


def plot_detection(summary: dict[str, Any], plan: StudyPlan, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for effect in EFFECTS:
        rates = [summary["detection"][effect][s]["rate"] for s in plan.scales]
        ax.plot(plan.scales, rates, marker="o", label=effect)
    ax.axhline(DETECTION_TARGET, color="grey", ls="--", lw=1, label=f"{DETECTION_TARGET:.0%} target")
    ax.set_xscale("log", base=2)
    ax.set_xticks(plan.scales, [f"{s:g}" for s in plan.scales])
    ax.set_ylim(-0.03, 1.03)
    ax.set_xlabel("magnitude scale (1 = realistic concealed magnitude)")
    ax.set_ylabel("detection rate (named effect = truth)")
    ax.set_title(f"Detection rate vs magnitude ({plan.effect_seeds} seeds per point)")
    ax.legend(fontsize=8, loc="lower right")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_ratios(summary: dict[str, Any], plan: StudyPlan, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(8, 4.2))
    rng = np.random.default_rng(0)
    markers = ["v", "s", "o", "^", "D", "P"]
    for j, scale in enumerate(plan.scales):
        labelled = False
        for x, effect in enumerate(EFFECTS):
            ratios = summary["detection"][effect][scale]["ratios"]
            if not ratios:
                continue
            offset = (j - (len(plan.scales) - 1) / 2) * 0.8 / len(plan.scales)
            jitter = rng.uniform(-0.06, 0.06, len(ratios))
            ax.scatter(x + offset + jitter, ratios, s=16, alpha=0.7, marker=markers[j % len(markers)], color=f"C{j}",
                       label=None if labelled else f"scale {scale:g}")
            labelled = True
    ax.axhline(RATIO_TARGET, color="red", ls="--", lw=1, label=f"requirement {RATIO_TARGET:g}×")
    ax.axhline(1.0, color="grey", ls=":", lw=1)
    ax.set_xticks(range(len(EFFECTS)), [SHORT[e] for e in EFFECTS])
    ax.set_ylabel("verify RMS after / floor")
    ax.set_title("Held-out error after the refit relative to the noise floor (correct detections)")
    ax.legend(fontsize=8, ncol=2)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_examples(results: list[dict[str, Any]], n_measure: int, path: Path) -> bool:
    examples = [r for r in results if "example" in r]
    if not examples:
        return False
    fig, axes = plt.subplots(len(examples), 2, figsize=(10, 2.1 * len(examples)), sharex=True, squeeze=False)
    for row, r in enumerate(examples):
        before, after = 1000 * r["example"]["before_mm"], 1000 * r["example"]["after_mm"]
        lim = 1.1 * max(np.abs(before).max(), np.abs(after).max())
        for col, (data, label) in enumerate(((before, "geometry only"), (after, f"geometry + {r['named']}"))):
            ax = axes[row, col]
            for leg in range(6):
                ax.plot(np.arange(1, len(data) + 1), data[:, leg], lw=0.9, label=f"leg {leg + 1}")
            ax.axvline(n_measure + 0.5, color="grey", ls="--", lw=0.8)
            ax.set_ylim(-lim, lim)
            ax.set_title(f"truth {r['effect']} (seed {r['seed']}): {label}", fontsize=8)
            ax.tick_params(labelsize=7)
            if col == 0:
                ax.set_ylabel("residual (µm)", fontsize=8)
    axes[0, 1].legend(fontsize=6, ncol=3, loc="upper right")
    for ax in axes[-1]:
        ax.set_xlabel("row (measure | verify)", fontsize=8)
    fig.suptitle("Per-leg length residuals at scale 1 (leg length implied by the measured pose minus recorded)",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return True


# ---------------------------------------------------------------------------------------------- document


def _pct(x: float) -> str:
    return "–" if not np.isfinite(x) else f"{100 * x:.0f}%"


def _f(x: float, fmt: str = ".2f") -> str:
    return "–" if x is None or not np.isfinite(x) else format(x, fmt)


def _smallest_text(v: float | None, scales: Sequence[float]) -> str:
    if v is None:
        return f"> {max(scales):g} (not reached)"
    return f"≤ {v:g} (lowest tested)" if v == min(scales) else f"{v:g}"


def write_doc(summary: dict[str, Any], plan: StudyPlan, elapsed_s: float, command: str, jobs: int,
              images: dict[str, str]) -> str:
    now = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    det, fa = summary["detection"], summary["false_alarms"]
    scales = plan.scales
    s1 = summary["confusion_scale"]
    lines = [
        "# Diagnosis study: detection power, refit quality and false alarms\n",
        f"Generated by `{command}` on {now} ({'QUICK, reduced plan' if plan.quick else 'full run'}; "
        f"{elapsed_s:.0f} s on {platform.machine()} with {jobs} worker process(es), {os.cpu_count()} CPUs, "
        f"Python {platform.python_version()}). Every number below comes from that run; rerun the command to "
        "regenerate this file and the plots `docs/img/diagnosis_*.png`.\n",
        "## Setup\n",
        f"- Robot: `hilcal.robot.default_robot()` (the paper robot). Measurement plan: "
        f"`factorial_exchange(robot, {N_MEASURE})` (computed once), then {N_VERIFY} verification poses "
        f"(`verification_poses(robot, {N_VERIFY}, seed={VERIFY_SEED})`), 45 s per pose, all simulated with "
        "`procedures.simulated_recording.simulate_with_truth`.",
        f"- Effect recordings: Table 2 geometric errors, Gaussian CMM noise (0.005 mm per sphere coordinate), one "
        f"effect from `concealed_effect_config(effect, scale, seed)` for scales {', '.join(f'{s:g}' for s in scales)} "
        f"and seeds 0–{plan.effect_seeds - 1} (rig seed = effect seed = bootstrap seed; the same seed draws the same "
        "per-leg values at every scale, so the scales are common-random-number comparisons).",
        f"- Null recordings: no effect, geometric errors `random_errors(seed, {NULL_GEOMETRY_SIGMA_MM})`, "
        f"{plan.null_seeds} seeds ({NULL_SEED_OFFSET}–{NULL_SEED_OFFSET + plan.null_seeds - 1}) for each CMM noise "
        f"model ({', '.join(NOISE_MODELS)}).",
        f"- `diagnose(rec, robot, alpha={ALPHA}, n_boot={plan.n_boot}, seed=seed)`. Detection = the named effect "
        "equals the concealed one (a detection flagged as indistinguishable from another candidate still counts, "
        "and is reported in the *ambiguous* column).",
        "- Verify RMS position error on the 24 verify rows: **before** = geometry-only calibration, **after** = "
        "geometry + named effect (the diagnosis's `before`/`after`), **floor** = measured vs the rig's true pose "
        "(what the true physics would give: measurement noise only). Requirement: after/floor ≤ "
        f"{RATIO_TARGET:g}.",
        "- **Signature size** = RMS over all 56 rows of the platform position shift caused by the effect: the "
        "rig's true pose with the effect minus the true pose a rigid rig (same errors, effect off) takes at the "
        "same reported leg lengths, in µm. It includes the part of the effect that the geometric parameters can "
        "absorb (e.g. a constant leg offset, the mean thermal growth), so it is an upper bound on what the "
        "diagnosis can see.",
        "- CV gain = relative reduction of the leave-one-pose-out residual (whitened units) from the geometry-only "
        "fit to geometry + effect (`cv_rms_geometry_mm` → `cv_rms_effect_mm`).",
        "",
    ]

    # ------------------------------------------------------------------ summary
    at1 = {e: det[e][s1]["rate"] for e in EFFECTS}
    meets_det = [e for e in EFFECTS if at1[e] >= DETECTION_TARGET]
    lines += ["## Summary\n"]
    lines.append(
        f"- Detection at scale {s1:g}: " + ", ".join(f"{e} {_pct(at1[e])}" for e in EFFECTS) + ". "
        + (f"All five reach the {DETECTION_TARGET:.0%} detection level." if len(meets_det) == len(EFFECTS) else
           f"Below {DETECTION_TARGET:.0%}: " + ", ".join(e for e in EFFECTS if e not in meets_det) + ".")
    )
    lines.append(
        f"- Smallest tested magnitude scale from which detection stays ≥ {DETECTION_TARGET:.0%}: "
        + ", ".join(f"{e} {_smallest_text(v, scales)}" for e, v in summary["smallest_detectable"].items()) + "."
    )
    ratio_ok = summary["ratio_over_target"] == 0
    lines.append(
        f"- After/floor on the verify rows over all {summary['n_hits']} correct detections: median "
        f"{_f(summary['ratio_median'])}, max {_f(summary['ratio_max'])} — "
        + ("the ≤ 1.5× requirement holds in every case." if ratio_ok else
           f"**the ≤ {RATIO_TARGET:g}× requirement is missed in {summary['ratio_over_target']} case(s)** "
           "(see the refit table).")
    )
    fa_all = fa["all"]
    fa_bad = [m for m in NOISE_MODELS if fa[m]["rate"] > FALSE_ALARM_TARGET]
    fa_unproven = [m for m in NOISE_MODELS if fa[m]["rate"] <= FALSE_ALARM_TARGET < fa[m]["ci"][1]]
    fa_text = "; ".join(
        f"{m} {fa[m]['k']}/{fa[m]['n']} = {_pct(fa[m]['rate'])} (95% CI {100 * fa[m]['ci'][0]:.1f}–"
        f"{100 * fa[m]['ci'][1]:.1f}%)" for m in NOISE_MODELS
    )
    lines.append(
        f"- False alarms on null recordings: {fa_text}; pooled {fa_all['k']}/{fa_all['n']} = {_pct(fa_all['rate'])} "
        f"(95% CI {100 * fa_all['ci'][0]:.1f}–{100 * fa_all['ci'][1]:.1f}%). "
        + ("Every point estimate is within the ≤ 5% target" if not fa_bad else
           f"**The ≤ 5% target is missed for {', '.join(fa_bad)}**")
        + ("; " + ("the pooled upper confidence bound is also below 5%, so the target is demonstrated overall"
                   if fa_all["ci"][1] <= FALSE_ALARM_TARGET else
                   "the pooled upper confidence bound exceeds 5%, so these runs cannot demonstrate the target at "
                   "95% confidence (more null runs would be needed)"))
        + (f". Not demonstrated at 95% confidence for {', '.join(fa_unproven)} (upper bound above 5%)."
           if fa_unproven else ".") + "\n"
    )

    # ------------------------------------------------------------------ detection
    head = "| effect | " + " | ".join(f"scale {s:g}" for s in scales) + " | detectable (≥ 80%) from scale |"
    lines += [
        "## Detection rate vs magnitude\n",
        f"Named effect = truth, hits/runs ({plan.effect_seeds} seeds per cell). See "
        f"`{images['detection']}`.\n",
        head,
        "|" + "---|" * (len(scales) + 2),
    ]
    for e in EFFECTS:
        cells = [f"{det[e][s]['hits']}/{det[e][s]['n']} ({_pct(det[e][s]['rate'])})" for s in scales]
        v = summary["smallest_detectable"][e]
        lines.append(f"| {e} | " + " | ".join(cells) + f" | {_smallest_text(v, scales)} |")
    lines += [
        "",
        "Signature size (median over seeds of the RMS true-pose position shift caused by the effect, µm) and the "
        "verify error left by a geometry-only calibration relative to the floor (median before/floor, all runs):\n",
        "| effect | " + " | ".join(f"scale {s:g}" for s in scales) + " |",
        "|" + "---|" * (len(scales) + 1),
    ]
    for e in EFFECTS:
        cells = [f"{_f(det[e][s]['signature_um'], '.0f')} µm, {_f(det[e][s]['before_ratio_median'])}×"
                 for s in scales]
        lines.append(f"| {e} | " + " | ".join(cells) + " |")
    lines.append("")

    # ------------------------------------------------------------------ confusion
    lines += [
        f"## Confusion at scale {s1:g}\n",
        f"Rows: concealed effect; columns: what the diagnosis named ({plan.effect_seeds} runs per row). "
        "*Ambiguous* counts correct detections that were reported as indistinguishable from another candidate.\n",
        "| truth \\ named | " + " | ".join(SHORT[o] for o in OUTCOMES) + " | ambiguous |",
        "|" + "---|" * (len(OUTCOMES) + 2),
    ]
    for e in EFFECTS:
        row = summary["confusion"][e]
        cells = [f"**{row[o]}**" if o == e else str(row[o]) for o in OUTCOMES]
        lines.append(f"| {e} | " + " | ".join(cells) + f" | {det[e][s1]['ambiguous']} |")
    lines.append("")

    # ------------------------------------------------------------------ refit
    lines += [
        "## Held-out improvement of the refit (correct detections)\n",
        f"Medians over the correct detections of each cell; verify RMS position error in µm. Requirement: "
        f"after/floor ≤ {RATIO_TARGET:g}. The last column is the worst after/floor over *all* runs of the cell, "
        f"misses included (a miss keeps the geometry-only error). See `{images['ratios']}`.\n",
        "| effect | scale | correct | before | after | floor | after/floor median | after/floor max | "
        "> 1.5× | CV gain | all runs: after/floor max |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for e in EFFECTS:
        for s in scales:
            d = det[e][s]
            lines.append(
                f"| {e} | {s:g} | {d['hits']}/{d['n']} | {_f(d['before_um'], '.1f')} | {_f(d['after_um'], '.1f')} | "
                f"{_f(d['floor_um'], '.1f')} | {_f(d['ratio_median'])} | {_f(d['ratio_max'])} | "
                f"{d['ratio_over_target']} | {_f(d['cv_gain_pct'], '.0f')}% | {_f(d['all_ratio_max'])} |"
            )
    lines.append("")
    ab = summary["thermal_sensor_ablation"]
    lines += [
        "### Thermal expansion: the temperature input\n",
        "The thermal candidate is driven by the recorded `temp_c`, which carries the rig's temperature-sensor "
        "noise (0.05 K). At scale s the legs grow ~50·s µm/K, so that noise would become ~2.5·s µm of leg-length "
        "error per row, which the floor (the rig's true pose) does not see; `hilcal.physics` therefore smooths "
        "`temp_c` over neighbouring rows (local linear, 7 rows: leg temperature changes over minutes) before "
        "using it. Ablation in this run: the same thermal recordings at scale "
        f"{ab['scale']:g} with a perfect sensor (`sensor_noise_k = 0`):\n",
        "| temperature sensor | correct | after/floor median | after/floor max |",
        "|---|---|---|---|",
        f"| 0.05 K (default) | {len(ab['noisy'])}/{ab['n']} | {_f(_median(ab['noisy']))} | {_f(_max(ab['noisy']))} |",
        f"| perfect | {ab['perfect_hits']}/{ab['n']} | {_f(_median(ab['perfect']))} | {_f(_max(ab['perfect']))} |",
        "",
        ("So most of the excess is an errors-in-variables limit of the temperature input (a better sensor or "
         "averaging several readings per pose would remove it), not a defect of the thermal model or the refit."
         if _median(ab["perfect"]) < 0.5 * (1 + _median(ab["noisy"])) else
         "The perfect sensor does not remove most of the excess, so the sensor noise is not the main cause."),
        "",
    ]

    # ------------------------------------------------------------------ false alarms
    lines += [
        "## False alarms on null recordings\n",
        "A false alarm is any outcome other than `none`: a named effect or `unexplained`. 95% Clopper–Pearson "
        f"intervals. Target ≤ {FALSE_ALARM_TARGET:.0%}.\n",
        "| CMM noise model | runs | named effect | unexplained | false-alarm rate | 95% CI | what was named | "
        "floor (µm) | geometry-only verify RMS (µm) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for m in [*NOISE_MODELS, "all"]:
        d = fa[m]
        lines.append(
            f"| {m if m != 'all' else '**pooled**'} | {d['n']} | {d['named']} | {d['unexplained']} | "
            f"{_pct(d['rate'])} | {100 * d['ci'][0]:.1f}–{100 * d['ci'][1]:.1f}% | {', '.join(d['which']) or '–'} | "
            f"{_f(d['floor_um'], '.1f')} | {_f(d['before_um'], '.1f')} |"
        )
    lines.append("")

    # ------------------------------------------------------------------ verdicts
    lines += ["## What meets the targets and what does not\n"]
    for e in EFFECTS:
        v = summary["smallest_detectable"][e]
        worst = _max([det[e][s]["ratio_max"] for s in scales])
        over = sum(det[e][s]["ratio_over_target"] for s in scales)
        lines.append(
            f"- **{e}**: detected in {_pct(at1[e])} of runs at scale {s1:g} "
            + (f"(meets {DETECTION_TARGET:.0%})" if at1[e] >= DETECTION_TARGET else
               f"(**misses {DETECTION_TARGET:.0%}**)")
            + "; " + (f"reliably detectable from scale {_smallest_text(v, scales)}" if v is not None else
                      "not reliably detectable at any tested scale")
            + f"; after/floor worst {_f(worst)} "
            + ("(meets ≤ 1.5×)." if over == 0 else f"(**{over} correct detection(s) above 1.5×**).")
        )
    for m in [*NOISE_MODELS, "all"]:
        d = fa[m]
        lo, hi = 100 * d["ci"][0], 100 * d["ci"][1]
        if d["rate"] <= FALSE_ALARM_TARGET:
            verdict = "meets the ≤ 5% target" + (
                f"; the 95% upper bound {hi:.1f}% is also below 5%, so the target is demonstrated"
                if hi <= 100 * FALSE_ALARM_TARGET else
                f", but with {d['n']} runs the 95% upper bound ({hi:.1f}%) does not exclude rates above 5%")
        else:
            verdict = "**misses the ≤ 5% target**" + (
                f" (the 95% lower bound {lo:.1f}% is above 5%: a real excess)" if lo > 100 * FALSE_ALARM_TARGET else
                f" (95% CI {lo:.1f}–{hi:.1f}%: not significantly above 5% with {d['n']} runs)")
        label = f"null, {m} noise" if m != "all" else "null, pooled over the noise models"
        lines.append(f"- **{label}**: false-alarm rate {d['k']}/{d['n']} = {_pct(d['rate'])} {verdict}.")
    lines += [
        "",
        "## Plots\n",
        f"- `{images['detection']}`: detection rate vs magnitude per effect.",
        f"- `{images['ratios']}`: after/floor per correct detection, per effect, coloured by scale.",
    ]
    if "examples" in images:
        lines.append(f"- `{images['examples']}`: one recording per effect (seed 0, scale 1): per-leg residuals of the "
                     "geometry-only fit and of the geometry + named-effect fit, measure rows then verify rows.")
    lines.append("")
    lines += [f"![detection rate]({Path(images['detection']).relative_to('docs')})",
              f"![after/floor]({Path(images['ratios']).relative_to('docs')})"]
    if "examples" in images:
        lines.append(f"![per-leg residuals]({Path(images['examples']).relative_to('docs')})")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------- entry points


def run(quick: bool, *, jobs: int | None = None, write: bool = True, progress: bool = True,
        command: str | None = None) -> dict[str, Any]:
    """Run the study (full or quick plan), write the doc and plots, and return the summary."""
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    plan = QUICK_PLAN if quick else FULL_PLAN
    jobs = jobs or min(2, os.cpu_count() or 1)
    robot = default_robot()
    t0 = time.perf_counter()
    if progress:
        columns = (TextColumn("{task.description:<36}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
        with Progress(*columns, console=Console(stderr=True)) as bar:
            results, measure = simulate_all(robot, plan, jobs, bar)
    else:
        results, measure = simulate_all(robot, plan, jobs, None)
    summary = summarize(results, plan)
    elapsed = time.perf_counter() - t0
    summary["elapsed_s"] = elapsed
    summary["plan"] = plan
    if write:
        IMG_DIR.mkdir(parents=True, exist_ok=True)
        images = {"detection": "docs/img/diagnosis_detection_rate.png", "ratios": "docs/img/diagnosis_after_floor.png"}
        plot_detection(summary, plan, ROOT / images["detection"])
        plot_ratios(summary, plan, ROOT / images["ratios"])
        if plot_examples(results, len(measure), ROOT / "docs/img/diagnosis_leg_residuals.png"):
            images["examples"] = "docs/img/diagnosis_leg_residuals.png"
        command = command or "python benchmarks/diagnosis_study.py" + (" --quick" if quick else "")
        DOC_PATH.write_text(write_doc(summary, plan, elapsed, command, jobs, images))
    for cell in summary["detection"].values():
        for d in cell.values():
            d.pop("ratios", None)
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 scales, 3 seeds, 10 null runs per noise model")
    parser.add_argument("--jobs", type=int, default=None, help="worker processes (default: min(2, CPUs))")
    args = parser.parse_args(argv)
    summary = run(args.quick, jobs=args.jobs)
    s1 = summary["confusion_scale"]
    print(f"diagnosis study: {summary['elapsed_s']:.0f} s; wrote {DOC_PATH.relative_to(ROOT)}")
    for e in EFFECTS:
        d = summary["detection"][e][s1]
        print(f"  {e:<24} detection@{s1:g} {d['hits']}/{d['n']}  smallest≥80%: {summary['smallest_detectable'][e]}"
              f"  after/floor median {d['ratio_median']:.2f} max {d['ratio_max']:.2f}")
    for m, d in summary["false_alarms"].items():
        print(f"  null {m:<10} {d['k']}/{d['n']} (named {d['named']}, unexplained {d['unexplained']}) "
              f"CI {100 * d['ci'][0]:.1f}-{100 * d['ci'][1]:.1f}%")
    print(f"  after/floor over all correct detections: median {summary['ratio_median']:.2f} "
          f"max {summary['ratio_max']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
