"""The gross-faults study (`make bench`, issue 33): can `hilcal run` measure a badly set-up machine, safely?

Why: the machines that need a calibration most are the badly set-up ones: a transducer gradient several percent
wrong, joints millimetres off, a CMM station aligned roughly, a dead transducer. Per case, the whole
`hilcal run --sim --yes` runs in a subprocess against the simulated controller (SLCAN and Modbus TCP) and CMM (a
pseudo-terminal) with the fault on the simulated rig, on three robots (the paper robot, examples/hexapod_small.toml,
examples/hexapod_stroke320.toml). The doc tabulates whether the run completed, the CMM's collisions, the measure
phase's time against the same robot's healthy rig, the verify-after RMS measured at the machine against the run's
diagnosis' prediction, and what the run said. The cases are in gross_faults_runs.py, the page in gross_faults_doc.py.

Run ``python benchmarks/studies/gross_faults_study.py [--quick] [--cases GLOB,...] [--jobs N]``; it writes
docs/gross_faults_study.md and the raw results, docs/gross_faults_study.json (from which ``--from-json`` writes the
doc again). ``--cases`` takes globs on the case ids (``paper/healthy``, ``small/gradient-1leg-4pc``,
``*/assembly-*``, ...; ``--list`` prints them); each chosen robot's healthy case always runs too.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from gross_faults_doc import write_doc  # noqa: E402
from gross_faults_runs import QUICK, ROOT, Case, cases, collisions_logged, run_case, select  # noqa: E402

DOC_PATH = ROOT / "docs" / "gross_faults_study.md"
JSON_PATH = ROOT / "docs" / "gross_faults_study.json"


def _guarded(case: Case, work: Path) -> dict[str, Any]:
    """run_case, with a failure of the study's own (a half-edited module it imports) reported as the case's."""
    try:
        return run_case(case, work)
    except Exception as e:  # one case's failure must not lose the others' results
        return {"id": case.id, "robot": case.robot, "name": case.name, "kind": case.kind, "label": case.label,
                "supported": True, "code": None, "status": None, "rows": {}, "collisions": None, "seconds": 0.0,
                "said": f"the study could not run it: {type(e).__name__}: {e}"}


def run_all(chosen: list[Case], work: Path, jobs: int) -> list[dict[str, Any]]:
    """Every case, `jobs` at a time; the results in the cases' order."""
    results: list[dict[str, Any]] = []
    with ThreadPoolExecutor(max(1, jobs)) as pool:
        futures = [pool.submit(_guarded, c, work) for c in chosen]
        for k, future in enumerate(futures, 1):
            r = future.result()
            results.append(r)
            print(f"[{k}/{len(futures)}] {r['id']}: exit {r['code']}, {r['status']}, {r['seconds']:.0f} s: "
                  f"{r['said'][:120]}", file=sys.stderr, flush=True)
    return results


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"a few cases: {', '.join(QUICK)}")
    parser.add_argument("--cases", help="comma-separated globs on the case ids (each robot's healthy case is added)")
    parser.add_argument("--list", action="store_true", help="print the case ids and exit")
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1), help="runs at once (at most 2)")
    parser.add_argument("--keep", type=Path, help="keep every run's folder under this folder (default: a "
                        "temporary folder, removed)")
    parser.add_argument("--doc", type=Path, default=DOC_PATH, help="where the page goes")
    parser.add_argument("--json", type=Path, default=JSON_PATH, help="where the raw results go")
    parser.add_argument("--from-json", type=Path, help="write the page again from an earlier run's raw results")
    args = parser.parse_args(argv)
    if args.from_json:
        saved = json.loads(args.from_json.read_text())
        args.doc.write_text(write_doc(saved["results"], saved["context"]))
        return 0
    every = cases()
    if args.list:
        print("\n".join(c.id for c in every))
        return 0
    patterns = args.cases.split(",") if args.cases else QUICK if args.quick else ["*"]
    chosen = select(every, patterns)
    if not chosen:
        parser.error(f"no case matches {args.cases!r} (see --list)")
    jobs = max(1, min(args.jobs, 2))
    command = "python benchmarks/studies/gross_faults_study.py" + (" --quick" if args.quick and not args.cases else "")
    command += f" --cases {args.cases}" if args.cases else ""
    started = datetime.datetime.now(datetime.UTC)
    t0 = time.perf_counter()
    work = args.keep or Path(tempfile.mkdtemp(prefix="hilcal-gross-faults-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        results = run_all(chosen, work, jobs)
    finally:
        if args.keep is None:
            shutil.rmtree(work, ignore_errors=True)
    context = {"command": command, "started_utc": started.strftime("%Y-%m-%d %H:%M"),
               "elapsed_s": time.perf_counter() - t0, "jobs": jobs, "n_cases": len(every),
               "machine": f"{platform.platform()}, {os.cpu_count()} CPUs, Python {platform.python_version()}",
               "collisions_logged": collisions_logged()}
    args.json.write_text(json.dumps({"context": context, "results": results}, indent=1) + "\n")
    args.doc.write_text(write_doc(results, context))
    print(f"wrote {args.doc} and {args.json} ({context['elapsed_s'] / 60:.1f} min)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
