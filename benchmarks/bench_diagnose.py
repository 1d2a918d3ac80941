"""How long `hilcal diagnose` takes on recordings shaped like real ones: the whole command (start-up included), the
function in-process, and the command with one other core busy.

The recordings are 168 rows each (108 measure rows in one session, 60 verify rows the next day): the real-shaped ones
of benchmarks/studies/diagnosis_real_shaped.py (a re-homing shift, a scale fault with a near-alias drive compliance,
a cyclic error and a base-joint-angle shape, one outlier), the size and shape of a real medium electric hexapod's
recording that took 9.8-12.7 s, and examples/electric_hexapod (three sessions, no outlier).

Run ``python benchmarks/bench_diagnose.py [--quick]``; it writes docs/benchmarks_diagnose.md. The target of issue 27
is <= 3 s on 2 cores for the whole command.
"""

from __future__ import annotations

import argparse
import logging
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

import structlog
from _docs import write_doc

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks" / "studies"))
from diagnosis_real_shaped import SEEDS, write  # noqa: E402

EXAMPLE = ROOT / "examples" / "electric_hexapod"
TARGET_S = 3.0


Times = tuple[list[float], list[float]]
"""Wall-clock seconds and CPU seconds (user + system, every thread) of each repeat."""


def _in_process(recording: Path, robot_path: Path, repeats: int) -> Times:
    from hilcal.discovery import diagnose
    from hilcal.recording import read_recording
    from hilcal.robot import load_robot

    robot = load_robot(robot_path)
    rec = read_recording(recording, robot)
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        diagnose(rec, robot)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return wall, cpu


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _command(recording: Path, robot_path: Path, repeats: int, env: dict[str, str]) -> Times:
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), _children_cpu_s()
        subprocess.run([sys.executable, "-m", "procedures.cli", "diagnose", str(recording), "--robot", str(robot_path),
                        "--json"], cwd=ROOT, env=env, check=True, capture_output=True)
        wall.append(time.perf_counter() - t0)
        cpu.append(_children_cpu_s() - c0)
    return wall, cpu


def _busy(n: int) -> list[subprocess.Popen[bytes]]:
    """n processes that keep a core busy (a loaded shop-floor PC)."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def _row(name: str, times: Times) -> str:
    wall, cpu = times
    met = "met" if statistics.median(wall) <= TARGET_S else "**not met**"
    return (f"| {name} | {statistics.median(wall):.2f} | {min(wall):.2f} | {max(wall):.2f} | "
            f"{statistics.median(cpu):.2f} | <= {TARGET_S:.0f} s: {met} |")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repeats")
    args = parser.parse_args(argv)
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    repeats = 2 if args.quick else 5
    load_before = os.getloadavg()[0]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    lines = ["| recording: what | median s | min s | max s | median CPU s | target (median wall) |",
             "|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory(prefix="hilcal-bench-diagnose-") as tmp:
        recordings = [(f"real-shaped seed {s}", path, Path(tmp) / "robot.toml")
                      for s, path in zip(SEEDS, write(Path(tmp)), strict=True)]
        recordings.append(("examples/electric_hexapod", EXAMPLE / "recording.csv", EXAMPLE / "robot.toml"))
        for name, path, robot in recordings:
            lines.append(_row(f"{name}: `hilcal diagnose --json` (start-up included)",
                              _command(path, robot, repeats, env)))
            lines.append(_row(f"{name}: `diagnose()` in-process", _in_process(path, robot, repeats)))
        hogs = _busy(1)
        try:
            for name, path, robot in recordings[:1]:
                lines.append(_row(f"{name}: `hilcal diagnose --json`, one other core busy",
                                  _command(path, robot, repeats, env)))
        finally:
            for h in hogs:
                h.kill()
    body = "\n".join(lines) + (
        "\n\nThe real-shaped recordings are made by `benchmarks/studies/diagnosis_real_shaped.py` (the same seeds "
        "every time): a medium electric hexapod (examples/import/logger's robot file), 108 measure rows on one day and "
        "60 verify rows the next, re-homed in between (a zero shift of tens of µm), one leg's mm per revolution off by "
        "0.5-1.5 % with drives soft enough to be its near-alias, a cyclic error over the stroke and a base universal "
        "joint with offset axes (both outside the library: generic terms), one measure row with a 0.2 mm probing "
        "error, no commanded poses, no temperature. Each takes two searches (the outlier is left out and the search "
        "runs again); the first stops at the step that finds the outlier. BLAS runs on one thread inside `diagnose` "
        "(threadpoolctl) and the bootstrap's largest products are split over two threads of its own.")
    write_doc("benchmarks_diagnose.md", "Diagnose on real-shaped recordings", "benchmarks/bench_diagnose.py",
              f"{repeats} repeats per row; load average {load_before:.1f} before the run and {os.getloadavg()[0]:.1f} "
              "after it (other work on this shared machine shows in the wall times; CPU s is user + system time of "
              "every thread, which it does not change).", body)
    print(body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
