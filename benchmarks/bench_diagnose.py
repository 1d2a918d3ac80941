"""How long `hilcal diagnose` takes on recordings shaped like real ones: the whole command (start-up included), the
function in-process, and the command with one other core busy.

The recordings are 168 rows each (108 measure rows in one session, 60 verify rows the next day): the real-shaped ones
of benchmarks/studies/diagnosis_real_shaped.py (a re-homing shift, a scale fault with a near-alias drive compliance,
a cyclic error and a base-joint-angle shape, one outlier), the size and shape of a real medium electric hexapod's
recording that took 9.8-12.7 s, and examples/electric_hexapod (three sessions, no outlier).

Wall seconds depend on the machine and on what else runs on it, so the example's command is also timed against a
reference workload in the same run, turn about (reference, command, reference, ...): fixed numpy work of the
diagnosis' kind on one BLAS thread (`_reference_workload`, never to be changed, or the ratios before it are lost).
The ratio command / reference is what issue 40 sets (at most 10.5x; 13.4x before it).

Run ``python benchmarks/bench_diagnose.py [--quick | --ratio-only]``; it writes docs/benchmarks_diagnose.md (not with
--ratio-only, which prints the ratios alone). The target of issue 27 is <= 3 s on 2 cores for the whole command.
"""

from __future__ import annotations

import argparse
import compileall
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

import numpy as np
import structlog
from _docs import write_doc
from threadpoolctl import threadpool_limits

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks" / "studies"))
from diagnosis_real_shaped import SEEDS, write  # noqa: E402

EXAMPLE = ROOT / "examples" / "electric_hexapod"
TARGET_S = 3.0
TARGET_RATIO = 10.5
"""Issue 40: `hilcal diagnose --json` of examples/electric_hexapod in at most 10.5 times the reference workload."""


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


ISSUE_40 = (
    "Issue 40 (the example's command at most 10.5 times the reference; 13.4 times before): py-spy over every thread "
    "and line_profiler on the hot functions showed the bootstrap's per-group sums (`np.add.reduceat` down the first "
    "axis cost as much as the products they sum; now rank by rank in numpy's own pairwise order, bit for bit the "
    "same), the candidate columns gathered, projected and concatenated again at every step (now one width-ordered "
    "block made once, projected in place, the bases multiplied straight into their place), the same fit, "
    "linearization and model state computed again (the geometry's twice, the final model's three times; now kept by "
    "parameter names and values), the regressors on the whole recording recomputed for every finite difference, "
    "and singular values of every pose in every forward kinematics call (now only where a Frobenius bound does not "
    "clear the pose). Independent work now runs on the second core: the near-aliases' separating poses while the "
    "rest of the answer is described, and the drop tests two at a time. The diagnosis' JSON is the same, bit for "
    "bit, on the examples and on simulated recordings with library and out-of-library effects; on the diagnosis "
    "study's quick cases it differs by at most one rounding (relative 2e-16).")


def _reference_workload() -> None:
    """The yardstick, fixed: on one BLAS thread, 5 rounds of what a diagnosis step does at the example's size (1008
    whitened residuals, a 60-column model, 1500 candidate columns, 1000 draws): a QR of the model, the candidates
    projected off it, a single-precision product with the draws, a batched small eigen-decomposition, a thin SVD."""
    rng = np.random.default_rng(40)
    model = rng.standard_normal((1008, 60))
    candidates = rng.standard_normal((1008, 1500))
    draws = rng.standard_normal((1008, 1000)).astype(np.float32)
    small = rng.standard_normal((500, 3, 3))
    with threadpool_limits(limits=1, user_api="blas"):
        for _ in range(5):
            q, _ = np.linalg.qr(model)
            projected = candidates - q @ (q.T @ candidates)
            np.sum((projected.T.astype(np.float32) @ draws) ** 2, axis=0)
            np.linalg.eigh(np.swapaxes(small, 1, 2) @ small)
            np.linalg.svd(projected[:, :200], full_matrices=False)


def _ratios(recording: Path, robot_path: Path, repeats: int, env: dict[str, str]) -> tuple[Times, Times]:
    """Turn about: the reference workload, then the command; (reference (wall, CPU) seconds, command / reference
    (wall, CPU) per pair)."""
    _reference_workload()  # warm: the first call pays numpy's and BLAS's first-use costs
    reference: Times = ([], [])
    ratio: Times = ([], [])
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        _reference_workload()
        reference[0].append(time.perf_counter() - t0)
        reference[1].append(time.process_time() - c0)
        wall, cpu = _command(recording, robot_path, 1, env)
        ratio[0].append(wall[0] / reference[0][-1])
        ratio[1].append(cpu[0] / reference[1][-1])
    return reference, ratio


def _ratio_rows(reference: Times, ratio: Times) -> list[str]:
    rows = []
    for k, what in enumerate(("wall", "CPU")):
        met = "met" if statistics.median(ratio[k]) <= TARGET_RATIO else "**not met**"
        rows.append(f"| examples/electric_hexapod: `hilcal diagnose --json` / reference workload, {what} seconds | "
                    f"{statistics.median(ratio[k]):.2f} | {min(ratio[k]):.2f} | {max(ratio[k]):.2f} | "
                    f"{statistics.median(reference[k]):.3f} | <= {TARGET_RATIO} x: {met} |")
    return rows


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
    parser.add_argument("--ratio-only", action="store_true", help="only the ratio to the reference workload")
    args = parser.parse_args(argv)
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    repeats = 2 if args.quick else 5
    load_before = os.getloadavg()[0]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MPLBACKEND": "Agg"}
    # Byte-compiled first, as an installation is (and as `make test` does): with PYTHONDONTWRITEBYTECODE set, every
    # start would otherwise compile the sources it imports again, and that is not the command's time.
    for package in ("hilcal", "procedures"):
        compileall.compile_dir(ROOT / package, quiet=1)
    ratio_lines = ["| ratio: what | median x | min x | max x | reference median s | target (median) |",
                   "|---|---|---|---|---|---|",
                   *_ratio_rows(*_ratios(EXAMPLE / "recording.csv", EXAMPLE / "robot.toml", 2 * repeats + 1, env))]
    if args.ratio_only:
        print("\n".join(ratio_lines))
        return 0
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
    body = "\n".join(ratio_lines) + "\n\n" + "\n".join(lines) + (
        "\n\nThe real-shaped recordings are made by `benchmarks/studies/diagnosis_real_shaped.py` (the same seeds "
        "every time): a medium electric hexapod (examples/import/logger's robot file), 108 measure rows on one day and "
        "60 verify rows the next, re-homed in between (a zero shift of tens of µm), one leg's mm per revolution off by "
        "0.5-1.5 % with drives soft enough to be its near-alias, a cyclic error over the stroke and a base universal "
        "joint with offset axes (both outside the library: generic terms), one measure row with a 0.2 mm probing "
        "error, no commanded poses, no temperature. Each takes two searches (the outlier is left out and the search "
        "runs again); the first stops at the step that finds the outlier. BLAS runs on one thread inside `diagnose` "
        "(threadpoolctl) and the bootstrap's largest products are split over two threads of its own. The ratio's "
        "reference workload is `_reference_workload` (fixed numpy work of a diagnosis step's kind on one BLAS "
        "thread), timed turn about with the command, each ratio from one adjacent pair; the sources are "
        "byte-compiled first.\n\n" + ISSUE_40)
    write_doc("benchmarks_diagnose.md", "Diagnose on real-shaped recordings", "benchmarks/bench_diagnose.py",
              f"{repeats} repeats per row; load average {load_before:.1f} before the run and {os.getloadavg()[0]:.1f} "
              "after it (other work on this shared machine shows in the wall times; CPU s is user + system time of "
              "every thread, which it does not change).", body)
    print(body)
    return 0


if __name__ == "__main__":
    sys.exit(main())
