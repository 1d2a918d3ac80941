"""The adaptive-plan study (`make bench`): does measuring until the accuracy is proven keep the accuracy of the fixed
plan in half its machine time, does a target hold, and does the diagnosis still find concealed physics?

Why: the fixed plan (32 D-optimal poses, one of them measured four times, 24 verify poses) takes the same hour of a
machine and its CMM whatever the machine needs. The adaptive plan (`hilcal.planning.sequential`) measures one pose
at a time and stops when its prediction of the verify-after maximum says so. On the in-process simulated station
(paper robot, Tables 2-5 and random geometric errors, 10 rig seeds each, the configured CMM noise) both plans are
walked on the same rig seeds, calibrated, "uploaded" in-process and verified with common CMM noise.

Run ``python benchmarks/studies/adaptive_study.py [--quick] [--jobs N]``; it writes docs/adaptive_study.md. Every
run is seeded, so the output is deterministic up to the date, the wall-clock times and the decision times.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import numpy as np
from adaptive_runs import (
    TABLES,
    TARGET_FACTOR,
    Case,
    fixed_plan_rows,
    floor_samples,
    init_worker,
    pre_motion_range,
    run_case,
    screening_power,
)
from adaptive_study_doc import write_doc
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

ROOT = Path(__file__).resolve().parents[2]
DOC_PATH = ROOT / "docs" / "adaptive_study.md"
FULL = {"seeds": 10, "physics_seeds": 10, "floor_rigs": 100, "improvements": (0.01, 0.02)}
SEED_STRIDE = 100
PHYSICS_SEED = 900
QUICK = {"seeds": 2, "physics_seeds": 1, "floor_rigs": 10, "improvements": (0.02,)}


def cases(plan: dict[str, Any]) -> list[Case]:
    """Ten rig seeds per error set, distinct across the sets (the rig seed draws the CMM noise, which dominates: the
    same seed on two tables would repeat nearly the same run), and the concealed-physics cases."""
    out = [Case(errors, SEED_STRIDE * k + seed) for k, errors in enumerate((*TABLES, "random"))
           for seed in range(plan["seeds"])]
    return out + [Case("table2", PHYSICS_SEED + seed, physics=True) for seed in range(plan["physics_seeds"])]


def run_all(todo: list[Case], jobs: int, initargs: tuple, progress: Progress) -> list[dict[str, Any]]:
    """Every case in the given order (independent of the worker count), physics cases first for load balance."""
    results: list[dict[str, Any] | None] = [None] * len(todo)
    task = progress.add_task("fixed and adaptive runs", total=len(todo))
    order = sorted(range(len(todo)), key=lambda i: (not todo[i].physics, i))
    if jobs <= 1:
        init_worker(*initargs)
        for i in order:
            results[i] = run_case(todo[i])
            progress.advance(task)
    else:
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ[var] = "1"
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(jobs, mp_context=ctx, initializer=init_worker, initargs=initargs) as ex:
            futures = {ex.submit(run_case, todo[i]): i for i in order}
            for fut in as_completed(futures):
                results[futures[fut]] = fut.result()
                progress.advance(task)
    return [r for r in results if r is not None]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two seeds per error set (for iterating)")
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="worker processes")
    parser.add_argument("--json", type=Path, help="also write the raw results here")
    args = parser.parse_args(argv)
    plan = QUICK if args.quick else FULL
    command = "python benchmarks/studies/adaptive_study.py" + (" --quick" if args.quick else "")
    t0 = time.perf_counter()
    init_worker()
    floors = floor_samples(plan["floor_rigs"])
    floor_mm = float(np.median(floors))
    target_mm = TARGET_FACTOR * floor_mm
    before_motion = pre_motion_range()
    columns = (TextColumn("{task.description:<32}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with Progress(*columns, console=Console(stderr=True)) as progress:
        results = run_all(cases(plan), args.jobs, (target_mm, plan["improvements"]), progress)
    plain = [r for r in results if not r["physics"]]
    designs = {json.dumps(r["adaptive"]["poses"]) for r in plain}
    stop_rows = np.array(plain[0]["adaptive"]["poses"])
    fixed_rows = fixed_plan_rows()
    power = {f"{c:g}": {"adaptive": screening_power(stop_rows, c), "fixed": screening_power(fixed_rows, c)}
             for c in (0.005, 0.0025)}
    elapsed = time.perf_counter() - t0
    context = {"distinct_designs": len(designs), "screening_power": power, "floors_mm": floors.tolist(),
               "floor_mm": floor_mm, "target_mm": target_mm, "jobs": args.jobs, "elapsed_s": elapsed,
               "command": command, "before_motion": before_motion, "plan": plan}
    if args.json:
        args.json.write_text(json.dumps({"context": context, "results": results}, indent=1, default=float))
    DOC_PATH.write_text(write_doc(results, context))
    print(f"wrote {DOC_PATH} ({elapsed:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
