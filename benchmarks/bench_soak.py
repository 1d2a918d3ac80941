"""Soak benchmark (`make bench`): many full `hilcal run --sim --yes` runs under shop-floor disturbances.

Why: a calibration of a real platform takes hours on a PC that also runs other software, over links that drop
for a moment. Per condition (CPU hogs on every core, heartbeat gaps, CMM silence and garbage, Modbus drops
during the upload, SIGKILL of the runner then resume) it reports runs completed and aborted (and why),
measurements lost or duplicated, parameter sets half-written on the controller, commands the controller
received while the link was down, and each completed run's calibrated verification error against an
undisturbed run of the same seed. Writes docs/reliability.md and docs/reliability.json.

Run ``python benchmarks/bench_soak.py [--runs N] [--jobs J] [--quick]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from _docs import DOCS, write_doc
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from soak_runs import CONDITIONS, Condition, SoakRun, soak_run

ROOT = Path(__file__).resolve().parents[1]


def _verify_cell(mine: list[SoakRun], reference: dict[int, SoakRun]) -> str:
    after = [r.verify_after_max_mm for r in mine if r.verify_after_max_mm is not None]
    ref = {seed: r.verify_after_max_mm for seed, r in reference.items() if r.verify_after_max_mm is not None}
    diffs = [abs(r.verify_after_max_mm - ref[r.seed]) for r in mine
             if r.verify_after_max_mm is not None and r.seed in ref]
    if not after:
        return "-"
    return f"{max(after):.4f}, {max(diffs):.4f}" if diffs else f"{max(after):.4f}, -"


def _row(cond: Condition, mine: list[SoakRun], reference: dict[int, SoakRun]) -> str:
    aborted = [r for r in mine if not r.completed]
    why = "; ".join(sorted({(r.abort_reason or "?")[:120] for r in aborted})) or "-"
    holds = " / ".join(str(sum(r.holds.get(link, 0) for r in mine)) for link in ("controller", "cmm", "modbus"))
    cells = [f"{cond.name}: {cond.title}", len(mine), len(mine) - len(aborted), f"{len(aborted)} ({why})",
             sum(r.lost for r in mine), sum(r.duplicated for r in mine),
             sum(r.live_set == "half-written" for r in mine), sum(r.late_commands for r in mine), holds,
             f"{max(r.wall_s for r in mine):.0f}", _verify_cell(mine, reference)]
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _table(runs: list[SoakRun], reference: dict[int, SoakRun]) -> str:
    lines = ["| condition | runs | completed | aborted (why) | lost | duplicated | half-written sets | "
             "commands in a gap | holds (controller / CMM / Modbus) | longest wall time (s) | "
             "verify max after (mm): worst, and worst difference to the undisturbed run |",
             "| --- | ---: | ---: | --- | ---: | ---: | ---: | ---: | --- | ---: | --- |"]
    for cond in CONDITIONS:
        mine = [r for r in runs if r.condition == cond.name]
        if mine:
            lines.append(_row(cond, mine, reference))
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10, help="runs per condition (seeds 1..N)")
    parser.add_argument("--jobs", type=int, default=2, help="runs at once, except under CPU hogs (always alone)")
    parser.add_argument("--quick", action="store_true", help="2 runs per condition")
    args = parser.parse_args(argv)
    n = 2 if args.quick else args.runs
    seeds = list(range(1, n + 1))
    runs: list[SoakRun] = []
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="hilcal-soak-") as tmp, Progress(
            TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()) as bar:
        task = bar.add_task("soak runs", total=n * len(CONDITIONS))

        def one(cond: Condition, seed: int) -> SoakRun:
            run = soak_run(cond, seed, Path(tmp) / f"{cond.name}-{seed}")
            bar.advance(task)
            bar.console.print(f"{cond.name} seed {seed}: {'completed' if run.completed else 'ABORTED'} "
                              f"in {run.wall_s:.0f} s, holds {run.holds}, live set {run.live_set}")
            return run

        for cond in CONDITIONS:
            jobs = 1 if cond.hogs else args.jobs
            with ThreadPoolExecutor(max_workers=jobs) as pool:
                runs += list(pool.map(lambda s, c=cond: one(c, s), seeds))
    reference = {r.seed: r for r in runs if r.condition == "undisturbed"}
    faulted = [r for r in runs if r.condition != "undisturbed"]
    table = _table(runs, reference)
    print(table)
    totals = (f"Over {len(faulted)} faulted runs: {sum(r.completed for r in faulted)} completed, "
              f"{sum(r.lost for r in faulted)} measurements lost, {sum(r.duplicated for r in faulted)} duplicated, "
              f"{sum(r.live_set == 'half-written' for r in faulted)} parameter sets half-written, "
              f"{sum(r.late_commands for r in faulted)} commands received while the link was down.")
    print(totals)
    (DOCS / "reliability.json").write_text(json.dumps([r.to_json() for r in runs], indent=1))
    write_doc("reliability.md", "Reliability: the soak benchmark", "benchmarks/bench_soak.py" +
              (" --quick" if args.quick else f" --runs {n}"),
              f"{n} runs per condition, seeds 1..{n} (rig seed and plan seed), {args.jobs} at a time except under "
              f"CPU hogs; {time.monotonic() - t0:.0f} s in all.", _body(table, totals))
    return 0


def _body(table: str, totals: str) -> str:
    return f"""Each run is a full `hilcal run --sim --yes` (83 measured poses, identification, upload, verification)
against the simulated devices over their real transports (SLCAN on a pty, Modbus TCP, the CMM's serial line
on a pty). A run killed with SIGKILL is resumed with `hilcal run --resume RUN_ID --out DIR`, as an operator
would; a run that stops by itself counts as aborted, with its message. Columns:

- **lost / duplicated**: measurement rows missing from a completed run's journal, or present twice.
- **half-written sets**: the simulator's live parameter set after the run is neither the set before the
  upload nor the uploaded one.
- **commands in a gap**: frames other than an e-stop that reached the simulated controller more than
  0.2 s into a link gap (0.1 s heartbeat timeout + 0.1 s for frames already in flight), i.e. sent after the
  host could know the link was down. The simulator records them itself (`gap_log`).
- **holds**: journaled `link_hold` events (the run held, waited for the link, checked and went on).
- **verify max after**: the calibrated maximum position error at the 24 verification poses, and its largest
  difference to the undisturbed run of the same seed (same rig, plan and noise
  seeds: a run that rode through its faults measures the same numbers; a resumed run differs slightly, as
  its restarts change when each pose is measured).

{totals}

{table}

The link policy is the station's `[links]` section (`procedures/link_guard.py`): heartbeats later than
0.1 s hold the run (the driver sends nothing but an e-stop), the run ends only after 1 s without one; the
CMM and Modbus steps are retried after a short wait, at most 2 and 3 times; every hold is journaled and
reported per link. Raw results: [reliability.json](reliability.json).
"""


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    sys.exit(main())
