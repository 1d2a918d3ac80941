"""Reproduce the identification simulations of Yu 2022 (section 5.2) and the LS vs L-infinity comparison of its
Table 7 on the simulated rig, then write docs/paper_study.md and its plots in docs/img/.

Why: the paper claims that L-infinity identification bounds the worst verification error better than least
squares, that D-optimal pose sets beat random ones, and that accuracy tracks measurement noise. This script checks
those claims on our independent truth rig (sim_devices) with our identification code (hilcal), seeded and
deterministic, so the doc can be regenerated at any time: ``python benchmarks/studies/paper_study.py [--quick]``.

This script runs the study: ``paper_study_runs.py`` computes, ``paper_study_plots.py`` draws and
``paper_study_doc.py`` writes the doc.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from collections.abc import Callable, Sequence

import structlog
from paper_study_doc import write_doc
from paper_study_plots import plot_ident_vs_pose_set, plot_per_pose, plot_reduction_vs_noise, plot_scenarios
from paper_study_runs import DOC_PATH, FULL_PLAN, IMG_DIR, QUICK_PLAN, ROOT, run_grid, run_table7, self_check
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from hilcal.robot import default_robot


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny grid, a few seeds (for iterating)")
    args = parser.parse_args(argv)
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    plan = QUICK_PLAN if args.quick else FULL_PLAN
    command = "python benchmarks/studies/paper_study.py" + (" --quick" if args.quick else "")
    robot = default_robot()
    t0 = time.perf_counter()
    check = self_check(robot)
    if check > 1e-6:
        raise SystemExit(f"self-check failed: measurement path differs from simulate_recording by {check}")
    console = Console(stderr=True)
    columns = (TextColumn("{task.description:<48}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=console) as progress:
        grid = run_grid(robot, plan, progress)
        t7 = run_table7(robot, plan, progress)
    elapsed = time.perf_counter() - t0
    IMG_DIR.mkdir(parents=True, exist_ok=True)
    focus = "set3_factorial_exchange32" if "set3_factorial_exchange32" in plan.pose_sets else plan.pose_sets[-1]
    plots: list[tuple[Callable[..., None], tuple]] = [
        (plot_ident_vs_pose_set, (grid, plan, IMG_DIR / "ident_error_vs_pose_set.png")),
        (plot_reduction_vs_noise, (grid, plan, focus, IMG_DIR / "reduction_vs_noise.png")),
        (plot_per_pose, (t7, plan.t7_seeds[0], IMG_DIR / "verification_per_pose.png")),
        (plot_scenarios, (t7, IMG_DIR / "linf_vs_ls_scenarios.png")),
    ]
    for fn, fn_args in plots:
        fn(*fn_args)
    DOC_PATH.parent.mkdir(parents=True, exist_ok=True)
    DOC_PATH.write_text(write_doc(grid, t7, plan, check, elapsed, command, robot.characteristic_length_mm))
    print(f"paper study: {elapsed:.0f} s; wrote {DOC_PATH.relative_to(ROOT)} and {len(plots)} plots in "
          f"{IMG_DIR.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
