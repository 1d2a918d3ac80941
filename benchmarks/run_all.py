"""Run every benchmark (``make bench``): start-up, test suite, core, protocols, CMM, laser tracker, whole runs, machine
time, panel, records, soak, diagnosis speed, and the studies that generate docs (the paper's simulation study, missing
physics, the coverage of the stated standard errors, the digital twin, physics to the machine, the adaptive plan
in-process and as whole runs, gross set-up faults), in the order of SCRIPTS.
``--quick`` passes through.

Each script runs in its own interpreter so one cannot leak state (plot backends, logging) into the other.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

HERE = Path(__file__).resolve().parent
SCRIPTS = ("bench_startup.py", "bench_tests.py", "bench_core.py", "bench_protocols_controller.py", "bench_cmm.py",
           "bench_tracker.py", "bench_run.py", "bench_machine_time.py", "bench_panel.py", "bench_records.py",
           "bench_soak.py",
           "studies/paper_study.py", "bench_diagnose.py", "studies/diagnosis_study.py",
           "studies/coverage_study.py", "studies/diagnosis_twin.py", "studies/physics_study.py",
           "studies/adaptive_study.py", "studies/adaptive_run_study.py", "studies/gross_faults_study.py")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="reduced runs, passed to every benchmark")
    args = parser.parse_args(argv)
    extra = ["--quick"] if args.quick else []
    for script in SCRIPTS:
        t0 = time.perf_counter()
        done = subprocess.run([sys.executable, str(HERE / script), *extra], check=False)
        print(f"{script}: exit {done.returncode} after {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        if done.returncode != 0:
            return done.returncode
    return 0


if __name__ == "__main__":
    sys.exit(main())
