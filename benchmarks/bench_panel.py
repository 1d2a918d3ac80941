"""The operator panel in headless Chromium during `hilcal run --sim --yes --panel`: live-update latency from the
server's event to the page's updated DOM, and the README's screenshot of the panel mid-run.

Writes docs/benchmarks_panel.md and docs/img/panel_midrun.png (`make screenshot` runs only this).
Needs Debian's chromium and chromium-driver (`apt-get install -y chromium chromium-driver`).
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from _docs import write_doc  # noqa: E402
from tests.browser_support import chromium, free_port, latency_summary, text, wait_for  # noqa: E402

SHOT = ROOT / "docs" / "img" / "panel_midrun.png"


def _progress(driver) -> tuple[str, int]:
    match = re.fullmatch(r"(\w+) pose (\d+) of \d+", text(driver, "current-pose"))
    return (match[1], int(match[2])) if match else ("", 0)


def run_once(work: Path, shot_after: int) -> dict:
    """One simulated run with one browser watching; screenshot when `shot_after` poses are re-verified."""
    port = free_port()
    env = {**os.environ, "HILCAL_RECORDS": str(work / "records.sqlite")}
    log = work / "cli.log"
    with chromium() as browser:
        browser.set_window_size(1400, 1900)
        t0 = time.perf_counter()
        with log.open("w") as out:
            cmd = [sys.executable, "-m", "procedures.cli", "run", "--sim", "--yes", "--panel", "--port", str(port),
                   "--out", str(work / "run"), "--operator", "J. Smith"]
            proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, env=env)
        try:
            wait_for(lambda: "operator panel:" in log.read_text(), 60, "the panel URL")
            browser.get(f"http://127.0.0.1:{port}/")
            wait_for(lambda: _progress(browser)[0] == "verify_after" and _progress(browser)[1] > shot_after, 600,
                     "the re-verification mid-way")
            time.sleep(0.3)
            SHOT.parent.mkdir(parents=True, exist_ok=True)
            browser.save_screenshot(str(SHOT))
            code = proc.wait(600)
            wall = time.perf_counter() - t0
            latencies = browser.execute_script("return window.panel.latencies;")
        finally:
            if proc.poll() is None:
                proc.kill()
    if code != 0:
        raise RuntimeError(f"hilcal run --panel failed ({code}): {log.read_text()[-2000:]}")
    by_section: dict[str, list[float]] = {}
    for section, value in latencies:
        by_section.setdefault(section, []).append(float(value))
    return {"wall_s": wall, "all": latency_summary([float(v) for _, v in latencies]),
            "sections": {k: latency_summary(v) for k, v in sorted(by_section.items())}}


def _row(name: str, s: dict) -> str:
    return (f"| {name} | {s['n']} | {s['median_ms']:.1f} | {s['p95_ms']:.1f} | {s['max_ms']:.1f} | "
            f"{100 * s['within_500ms_fraction']:.1f} |")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="accepted for `make bench`; the run is the same")
    parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="hilcal-panel-bench-") as tmp:
        load_before = os.getloadavg()[0]
        result = run_once(Path(tmp), shot_after=12)
    header = ("| changes of | n | median (ms) | 95th pct (ms) | max (ms) | within 500 ms (%) |\n"
              "| --- | ---: | ---: | ---: | ---: | ---: |")
    rows = [_row("all sections", result["all"])] + [_row(k, v) for k, v in result["sections"].items()]
    body = (f"{header}\n" + "\n".join(rows) + "\n\n"
            f"Run wall time with the panel and one browser attached: {result['wall_s']:.1f} s "
            f"(1-min load average at start {load_before:.1f}).\n\n"
            f"![the panel mid-run](img/{SHOT.name})\n")
    detail = ("One `hilcal run --sim --yes --panel` (simulator as in `make demo`) watched by one headless Chromium "
              "(idle CPU priority) on the same machine. Latency: the wall time from a change of the panel's live "
              "state in the run's process (its `t` stamp) to the end of the animation frame that updated the page's "
              "DOM (`window.panel.latencies`); both clocks are the machine's. Changes are drawn once per frame, so "
              "a burst of changes is timed to the same frame. The screenshot is taken during the re-verification.")
    path = write_doc("benchmarks_panel.md", "Operator panel: live-update latency", "benchmarks/bench_panel.py", detail,
                     body)
    print(f"wrote {path} and {SHOT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
