"""Start-up of the command line: `hilcal --help`, `hilcal history --help` and `hilcal identify --help` as fresh
processes of the venv's `hilcal` entry point (median and max of repeated runs). Writes docs/benchmarks_startup.md.

The bare interpreter (`python -c pass`) is timed too: it is the floor no import change can go below.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from _docs import write_doc  # noqa: E402

TARGET_S = 0.3
"""Issue 22: every `--help` starts in at most 0.3 s."""
RUN_IMPORTS = "imports of hilcal run before its devices open (python -c)"
"""Paid by every start and resume of a run; plotting and statistics are loaded after the measurements."""


def hilcal_entry() -> Path:
    """The `hilcal` script next to this interpreter (the venv's), as an operator runs it."""
    path = Path(sys.executable).parent / "hilcal"
    if not path.exists():
        raise SystemExit(f"no {path}: install the project (`pip install -e .`) in this interpreter's venv")
    return path


def time_command(command: list[str], repeats: int) -> list[float]:
    """Wall seconds of `repeats` fresh runs of `command` (after one unmeasured run that warms the file cache)."""
    subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True, cwd=ROOT)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True, cwd=ROOT)
        times.append(time.perf_counter() - t0)
    return times


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="5 runs per command instead of 10")
    args = parser.parse_args(argv)
    repeats = 5 if args.quick else 10
    hilcal = str(hilcal_entry())
    commands = {"python -c pass (floor)": [sys.executable, "-c", "pass"],
                "hilcal --help": [hilcal, "--help"],
                "hilcal history --help": [hilcal, "history", "--help"],
                "hilcal identify --help": [hilcal, "identify", "--help"],
                RUN_IMPORTS: [sys.executable, "-c", "import procedures.cli.operator, procedures.cli.sim_station, "
                              "procedures.runner"]}
    load_before = os.getloadavg()[0]
    rows = ["| command | runs | median (s) | max (s) | within 0.3 s |", "| --- | ---: | ---: | ---: | --- |"]
    for name, command in commands.items():
        times = time_command(command, repeats)
        median, worst = statistics.median(times), max(times)
        within = "" if name.startswith(("python", RUN_IMPORTS)) else ("yes" if median <= TARGET_S else "**no**")
        rows.append(f"| `{name}` | {repeats} | {median:.3f} | {worst:.3f} | {within} |")
        print(f"{name}: median {median:.3f} s, max {worst:.3f} s", file=sys.stderr)
    body = ("\n".join(rows) + "\n\n"
            f"1-min load average at start {load_before:.1f}. The help of the app and of its commands imports no "
            "numpy, scipy, matplotlib, panel server, database or device protocol: each command imports what it "
            "uses (tests/cli/test_startup.py guards this by import tracing). What remains: the interpreter, typer "
            "with rich (the help's layout) and, for a command's help, pydantic (typer validates the app's options "
            "with it). `python -X importtime -m procedures.cli history --help` lists the imports one by one. "
            "A run (and each resume) imports the engine, the drivers, the journal and the records before it opens "
            "the devices; matplotlib and scipy.stats come after the measurements, for the report (the same test "
            "guards this).\n")
    detail = (f"Each command runs {repeats} times as a fresh process of the venv's `hilcal` script (after one "
              "unmeasured run); wall time with `time.perf_counter`.")
    path = write_doc("benchmarks_startup.md", "Command line: start-up time", "benchmarks/bench_startup.py", detail,
                     body)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
