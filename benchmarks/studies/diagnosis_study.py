"""The diagnosis study (`make bench`): how often `hilcal diagnose` gives the right answer, and what it buys.

Why: the diagnosis names missing physics, several effects at once, or says `unexplained` and still models what
no library effect describes. Before trusting it on the shop floor we need to know, on recordings where the truth
is known: how often both effects of a pair are named, how often physics the library does not list is called
`unexplained` (never "within noise") and how much the generic model gains on held-out poses, how often a
recording without any missing physics raises an alarm, with and without commanded poses and temperatures.

Run ``python benchmarks/studies/diagnosis_study.py [--quick] [--jobs N]``; it writes docs/diagnosis_study.md and
docs/img/diagnosis_*.png. Every run is seeded, so the output is deterministic (up to the date and run time).
"""

from __future__ import annotations

import argparse
import itertools
import logging
import multiprocessing
import os
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import structlog
from diagnosis_cases import ALPHA, N_MEASURE, N_VERIFY, NULL_GEOMETRY_SIGMA_MM, Case, init_worker, run_case
from diagnosis_doc import plot_singles, plot_unlisted, update_method_doc, write_doc
from diagnosis_faults import fault_section, run_fault_case, study_cases, summarize_faults, verdict_line
from diagnosis_summary import summarize
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from sim_devices.rig.config import EFFECT_NAMES
from sim_devices.rig.unlisted_concealed import UNLISTED_EFFECT_NAMES

ROOT = Path(__file__).resolve().parents[2]
DOC_PATH = ROOT / "docs" / "diagnosis_study.md"
NULL_SEED_OFFSET = 10_000
NOISE_MODELS = ("gaussian", "distance", "student_t")


@dataclass(frozen=True)
class StudyPlan:
    quick: bool
    single_scales: tuple[float, ...]
    single_seeds: int
    pair_seeds: int
    unlisted_scales: tuple[float, ...]
    unlisted_seeds: int
    bare_seeds: int
    null_seeds: int
    n_boot: int
    fault_grid_seeds: int = 5
    fault_done_when_seeds: int = 20
    outlier_seeds: int = 4


FULL_PLAN = StudyPlan(False, (0.5, 1.0, 2.0), 12, 10, (0.5, 1.0), 12, 8, 100, 999, 5, 20, 4)
QUICK_PLAN = StudyPlan(True, (1.0,), 2, 1, (1.0,), 2, 1, 4, 399, 1, 2, 1)
COMBOS = (("leg_compliance",), ("thermal_expansion",))
"""Library effects concealed together with each out-of-library effect (several effects at once)."""


def cases(plan: StudyPlan) -> list[Case]:
    out = [Case("single", (e,), s, seed) for e in EFFECT_NAMES for s in plan.single_scales
           for seed in range(plan.single_seeds)]
    out += [Case("single", (e,), 1.0, 100 + seed, bare=True) for e in EFFECT_NAMES if e != "thermal_expansion"
            for seed in range(plan.bare_seeds)]
    out += [Case("pair", pair, 1.0, 200 + seed) for pair in itertools.combinations(EFFECT_NAMES, 2)
            for seed in range(plan.pair_seeds)]
    out += [Case("unlisted", (u,), s, 300 + seed) for u in UNLISTED_EFFECT_NAMES for s in plan.unlisted_scales
            for seed in range(plan.unlisted_seeds)]
    out += [Case("combo", (u, *lib), 1.0, 400 + seed) for u in UNLISTED_EFFECT_NAMES for lib in COMBOS
            for seed in range(max(1, plan.unlisted_seeds // 2))]
    out += [Case("outlier", (e,), 1.0, 500 + seed, outliers=2) for e in EFFECT_NAMES
            for seed in range(plan.outlier_seeds)]
    out += [Case("null", (), 0.0, NULL_SEED_OFFSET + k, model) for model in NOISE_MODELS
            for k in range(plan.null_seeds)]
    out += [Case("null", (), 0.0, 2 * NULL_SEED_OFFSET + k, NOISE_MODELS[k % 3], bare=True)
            for k in range(plan.null_seeds)]
    return out


def _run(case: Any, n_boot: int) -> dict[str, Any]:
    return run_case(case, n_boot) if isinstance(case, Case) else run_fault_case(case, n_boot)


def run_all(plan: StudyPlan, jobs: int, progress: Progress | None) -> list[dict[str, Any]]:
    """Every case, in plan order (independent of the worker count); longest first for load balance."""
    todo: list[Any] = [*cases(plan), *study_cases(plan.fault_grid_seeds, plan.fault_done_when_seeds)]
    results: list[dict[str, Any] | None] = [None] * len(todo)
    task = progress.add_task("simulate + diagnose recordings", total=len(todo)) if progress else None
    order = sorted(range(len(todo)), key=lambda i: (getattr(todo[i], "kind", "") == "null",
                                                    -len(getattr(todo[i], "effects", ("a", "b", "c"))), i))
    if jobs <= 1:
        init_worker()
        for i in order:
            results[i] = _run(todo[i], plan.n_boot)
            if progress is not None and task is not None:
                progress.advance(task)
    else:
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = "1"
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(jobs, mp_context=ctx, initializer=init_worker) as ex:
            futures = {ex.submit(_run, todo[i], plan.n_boot): i for i in order}
            for fut in as_completed(futures):
                results[futures[fut]] = fut.result()
                if progress is not None and task is not None:
                    progress.advance(task)
    return [r for r in results if r is not None]


def setup_text(plan: StudyPlan) -> list[str]:
    return [
        f"- Robot: the paper robot (`default_robot()`); {N_MEASURE} D-optimal measure poses "
        f"(`factorial_exchange(robot, {N_MEASURE}, rng(0))`) and {N_VERIFY} verify poses, 45 s per pose, simulated by "
        "`procedures.cli.simulated_recording.simulate_with_truth` on the independent rig (Table 2 geometric errors, "
        "5 µm CMM noise per sphere coordinate unless stated).",
        f"- One library effect: `concealed_effect_config(effect, scale, seed)`, scales "
        f"{', '.join(f'{s:g}' for s in plan.single_scales)}, {plan.single_seeds} seeds each; plus "
        f"{plan.bare_seeds} seeds per effect at scale 1 written without cmd_* and temp_c.",
        f"- Pairs: every pair of the five library effects at scale 1, {plan.pair_seeds} seeds each.",
        f"- Outliers: each library effect at scale 1 with two measure rows given a gross position error of "
        f"0.1-0.5 mm (`plant_outliers`), {plan.outlier_seeds} seeds each.",
        f"- Out-of-library: every effect of `sim_devices.rig.unlisted_physics` "
        f"({', '.join(UNLISTED_EFFECT_NAMES)}), scales {', '.join(f'{s:g}' for s in plan.unlisted_scales)}, "
        f"{plan.unlisted_seeds} seeds; and each together with "
        f"{' or '.join(c[0] for c in COMBOS)} at scale 1.",
        f"- Nulls: no effect, geometric errors `random_errors(seed, {NULL_GEOMETRY_SIGMA_MM})`, {plan.null_seeds} "
        f"seeds per CMM noise model ({', '.join(NOISE_MODELS)}), and {plan.null_seeds} more without cmd_* and "
        "temp_c (noise models in turn).",
        f"- `diagnose(rec, robot, alpha={ALPHA}, n_boot={plan.n_boot}, seed=seed)`; the noise yardstick comes from "
        "the recording's `sphere_fit_rms_mm` column. Floor = verify RMS position error of the measured against "
        "the rig's true pose (what the true physics would give).",
    ]


def run(quick: bool, jobs: int | None = None, command: str | None = None) -> dict[str, Any]:
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    plan = QUICK_PLAN if quick else FULL_PLAN
    jobs = jobs or min(2, os.cpu_count() or 1)
    t0 = time.perf_counter()
    columns = (TextColumn("{task.description:<36}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=Console(stderr=True)) as bar:
        results = run_all(plan, jobs, bar)
    summary = summarize([r for r in results if r["kind"] != "fault"])
    faults = summarize_faults([r for r in results if r["kind"] == "fault"])
    elapsed = time.perf_counter() - t0
    images = {"naming rate vs magnitude": "docs/img/diagnosis_detection_rate.png",
              "out-of-library: before and after": "docs/img/diagnosis_unlisted.png"}
    (ROOT / "docs" / "img").mkdir(parents=True, exist_ok=True)
    plot_singles(summary, ROOT / images["naming rate vs magnitude"])
    plot_unlisted(summary, ROOT / images["out-of-library: before and after"])
    command = command or "python benchmarks/studies/diagnosis_study.py" + (" --quick" if quick else "")
    doc = write_doc(summary, setup_text(plan), command, elapsed, jobs, images)
    head, plots_part = doc.split("## Plots\n", 1)
    DOC_PATH.write_text(head + "\n".join(fault_section(faults)) + "\n## Plots\n" + plots_part)
    update_method_doc(ROOT / "docs" / "diagnosis.md", summary, command, [verdict_line(faults)])
    summary["elapsed_s"] = elapsed
    summary["faults"] = faults
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few seeds per case kind")
    parser.add_argument("--jobs", type=int, default=None, help="worker processes (default: min(2, CPUs))")
    args = parser.parse_args(argv)
    summary = run(args.quick, args.jobs)
    print(f"diagnosis study: {summary['elapsed_s']:.0f} s, {summary['n_runs']} recordings; wrote "
          f"{DOC_PATH.relative_to(ROOT)}")
    t = summary["pairs"]["total"]
    print(f"  pairs both named {t['k']}/{t['n']}; nulls {summary['nulls']['pooled']['k']}/"
          f"{summary['nulls']['pooled']['n']}; range violations {summary['range_violations']}")
    print("  " + verdict_line(summary["faults"]).lstrip("- "))
    return 0


if __name__ == "__main__":
    sys.exit(main())
