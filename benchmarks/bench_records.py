"""Records on PostgreSQL and SQLite: 10 concurrent writers x 100 whole runs (records per second, latency per run),
and `history` / `drift` on a machine with 10,000 calibrations (query time). Writes docs/benchmarks_records.md.

Each written run is what the runner stores at the end of a calibration: the run row, its 48 parameters with
standard errors and its upload with the audit row, in one transaction. The PostgreSQL server is a throw-away one
from Debian's binaries (tests/postgres_server.py) with durable commits (fsync on), on the same machine.
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks._docs import write_doc  # noqa: E402

NAMES = [f"leg{i}_{p}_mm" for i in range(1, 7) for p in ("a_x", "a_y", "a_z", "b_x", "b_y", "b_z", "l0",
                                                           "stroke_at_home")]
MACHINE = "paper-table1/BENCH-1"


def run_record(k: int, writer: int) -> tuple[dict, dict, list[dict]]:
    run_id = f"w{writer:02d}-{k:05d}"
    run = {"started_at": f"2026-10-01T{k // 3600 % 24:02d}:{k // 60 % 60:02d}:{k % 60:02d}+00:00",
           "status": "complete", "robot_name": "paper-table1", "machine_serial": f"W{writer}",
           "station": f"bay {writer}", "operator": "bench"}
    params = {name: (1000.0 + 0.001 * j, 0.002) for j, name in enumerate(NAMES)}
    upload = {"upload_id": f"{run_id}/upload", "operator": "bench",
              "record": {"operation": "upload", "outcome": "committed", "endpoint": "tcp://10.0.0.5:502",
                         "params_sha256": f"{k:064x}"}}
    return run, params, [upload]


def writer(target: str, index: int, runs: int, ready: Any, results: Any) -> None:
    from procedures.records import Records

    latencies = []
    with Records(target) as db:
        ready.wait(300)  # every writer connected: the clock starts
        for k in range(runs):
            run, params, uploads = run_record(k, index)
            t0 = time.perf_counter()
            db.save_run(f"w{index:02d}-{k:05d}", run, params, uploads)
            latencies.append(time.perf_counter() - t0)
    results.put(latencies)


def concurrent_writes(target: str, writers: int, runs: int) -> dict[str, float]:
    """`writers` processes, each writing `runs` whole runs as fast as it can, all starting together."""
    from procedures.records import Records

    Records(target).close()  # created and migrated before the clock starts
    ctx = multiprocessing.get_context("spawn")
    ready, results = ctx.Barrier(writers + 1), ctx.Queue()
    procs = [ctx.Process(target=writer, args=(target, i, runs, ready, results)) for i in range(writers)]
    for p in procs:
        p.start()
    ready.wait(300)
    t0 = time.perf_counter()
    latencies = np.concatenate([results.get(timeout=600) for _ in procs])
    wall = time.perf_counter() - t0
    for p in procs:
        p.join(60)
    with Records(target) as db, db.engine.connect() as conn:
        import sqlalchemy as sa

        stored = conn.execute(sa.text("SELECT COUNT(*) FROM runs")).scalar()
    if stored != writers * runs:
        raise RuntimeError(f"{stored} runs stored, {writers * runs} written")
    return {"runs": float(writers * runs), "wall_s": wall, "per_s": writers * runs / wall,
            "p50_ms": 1000 * float(np.percentile(latencies, 50)), "p95_ms": 1000 * float(np.percentile(latencies, 95)),
            "max_ms": 1000 * float(latencies.max())}


def fill_machine(target: str, n: int) -> None:
    """n calibrations of one machine (one bulk transaction: this is set-up, not what is measured)."""
    import sqlalchemy as sa

    from procedures.records import Records
    from procedures.records.schema import run_parameters, runs

    rng = np.random.default_rng(1)
    t0 = np.datetime64("2000-01-01T08:00:00")
    with Records(target) as db, db.engine.begin() as conn:
        run_rows = [{"run_id": f"h{j:06d}", "started_at": f"{t0 + np.timedelta64(j, 'D')}+00:00",
                     "status": "complete", "robot_name": "paper-table1", "machine": MACHINE} for j in range(n)]
        conn.execute(runs.insert(), run_rows)
        for start in range(0, n, 1000):
            conn.execute(run_parameters.insert(), [
                {"run_id": f"h{j:06d}", "name": name, "value_mm": 1000.0 + rng.normal(0, 0.002), "std_mm": 0.002}
                for j in range(start, min(n, start + 1000)) for name in NAMES])
        assert conn.execute(sa.text("SELECT COUNT(*) FROM run_parameters")).scalar() == n * len(NAMES)


def queries(target: str, repeat: int = 3) -> dict[str, float]:
    """Best of `repeat`: history (newest 20, and all), the calibrations' read, and drift on them."""
    from hilcal.drift import drift
    from procedures.records import Records

    best: dict[str, float] = {}

    def timed(key: str, fn: Any) -> Any:
        t0 = time.perf_counter()
        value = fn()
        best[key] = min(best.get(key, float("inf")), time.perf_counter() - t0)
        return value

    with Records(target) as db:
        for _ in range(repeat):
            timed("history_20_s", lambda: db.history(20, machine=MACHINE))
            timed("history_all_s", lambda: db.history(100_000, machine=MACHINE))
            cals = timed("read_calibrations_s", lambda: db.calibrations(MACHINE))
            result = timed("drift_s", lambda cals=cals: drift(cals, MACHINE))
    best["calibrations"] = float(len(cals))
    best["flags"] = float(len(result.flagged))
    return best


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="10 writers x 20 runs, 2,000 calibrations")
    args = parser.parse_args(argv)
    writers, runs, history_n = (10, 20, 2000) if args.quick else (10, 100, 10_000)
    from tests.postgres_server import pg_bin, postgres_server

    rows: dict[str, dict[str, dict[str, float]]] = {}
    with tempfile.TemporaryDirectory(prefix="hilcal-bench-records-") as tmp:
        targets = {"SQLite (WAL file)": lambda: str(Path(tmp) / f"r{time.monotonic_ns()}.sqlite")}
        server = None
        if pg_bin() is not None:
            server = postgres_server(fsync=True)
            pg = server.__enter__()
            targets["PostgreSQL (local server)"] = pg.new_database
        try:
            for engine, new_target in targets.items():
                print(f"{engine}: {writers} writers x {runs} runs", file=sys.stderr)
                writes = concurrent_writes(new_target(), writers, runs)
                print(f"{engine}: {history_n} calibrations of one machine", file=sys.stderr)
                target = new_target()
                fill_machine(target, history_n)
                rows[engine] = {"writes": writes, "queries": queries(target)}
        finally:
            if server is not None:
                server.__exit__(None, None, None)
    body = ["## Concurrent writers", "",
            f"{writers} processes write {runs} whole runs each at once (a run row, 48 parameters, one upload and its "
            "audit row per transaction).", "",
            "| engine | runs | wall (s) | runs per second | p50 latency (ms) | p95 latency (ms) | max (ms) |",
            "|---|---|---|---|---|---|---|"]
    for engine, r in rows.items():
        w = r["writes"]
        body.append(f"| {engine} | {w['runs']:.0f} | {w['wall_s']:.1f} | {w['per_s']:.0f} | {w['p50_ms']:.1f} | "
                    f"{w['p95_ms']:.1f} | {w['max_ms']:.0f} |")
    body += ["", f"## History and drift of a machine with {history_n:,} calibrations", "",
             "Best of three, in the process (the command line adds its start-up). `history` reads the runs with "
             "their uploads; drift reads every calibration's 48 parameters and compares them.", "",
             "| engine | history, newest 20 (ms) | history, all (s) | read calibrations (s) | drift (s) | flags |",
             "|---|---|---|---|---|---|"]
    for engine, r in rows.items():
        q = r["queries"]
        body.append(f"| {engine} | {1000 * q['history_20_s']:.1f} | {q['history_all_s']:.2f} | "
                    f"{q['read_calibrations_s']:.2f} | {q['drift_s']:.2f} | {q['flags']:.0f} |")
    if server is None:
        body += ["", "PostgreSQL was not measured: its server binaries are not installed (apt-get install "
                     "postgresql)."]
    detail = "Quick mode." if args.quick else "Full mode."
    path = write_doc("benchmarks_records.md", "Records benchmark: concurrent writers, history and drift",
                     "benchmarks/bench_records.py", detail, "\n".join(body))
    print(f"wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
