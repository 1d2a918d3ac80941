"""What the panel's browser tests share: starting `hilcal run --panel` and stopping it, the run's journal read
without disturbing it, what the page shows, and the page's measured update delays."""

from __future__ import annotations

import os
import re
import sqlite3
import subprocess
import sys
from pathlib import Path

from tests.cli.browser_support import LATENCIES_S, text, wait_for


def start_panel_run(tmp: Path, port: int, *args: str) -> tuple[subprocess.Popen, Path]:
    log = tmp / f"cli-{port}.log"
    env = {**os.environ, "HILCAL_RECORDS": str(tmp / "records.sqlite")}
    cmd = [sys.executable, "-m", "procedures.cli", "run", "--panel", "--port", str(port), *args]
    with log.open("w") as out:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, env=env)
    wait_for(lambda: "operator panel: http://127.0.0.1:" in log.read_text() or proc.poll() is not None, 60,
             "the panel's URL")
    assert proc.poll() is None, log.read_text()
    return proc, log


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.wait(10)


def journal_rows(out: Path, sql: str) -> list[tuple]:
    db = sqlite3.connect(f"file:{out / 'journal.sqlite'}?mode=ro", uri=True, timeout=2)
    try:
        return db.execute(sql).fetchall()
    finally:
        db.close()


def done_count(driver) -> int:
    match = re.fullmatch(r"(\d+) of (\d+)", text(driver, "done-count"))
    return int(match[1]) if match else -1


def page_view(driver) -> dict[str, object]:
    """What an operator reads on the page (the parts that do not tick by themselves)."""
    return {key: text(driver, key) for key in ("status", "done-count", "current-pose", "question-text",
                                               "identification", "plan-table", "verification-summary")} | {
        "points": len(driver.find_elements("css selector", "#errors circle")),
        "timeline": text(driver, "timeline").count("\n")}


def collect_latency(driver) -> None:
    values = driver.execute_script("return window.panel.latencies.map(x => x[1]);")
    LATENCIES_S.extend(float(v) for v in values)


