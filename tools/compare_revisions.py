"""Proof that a refactoring changed no behaviour: the demo run's report.json and `hilcal diagnose --json` on
examples/small_hexapod, produced by two revisions, must be identical apart from times, run ids and endpoints.

    python tools/compare_revisions.py BEFORE [AFTER]

BEFORE and AFTER are git revisions (AFTER defaults to the working tree). Each revision is checked out into a
temporary git worktree and run with this interpreter, so both use the same installed libraries. Exit 0 when the
outputs are identical, 1 with the differing fields otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
VOLATILE_KEYS = {"run_id", "endpoint", "started_at", "finished_at", "at", "actual_s", "actual_over_estimated",
                 "out_dir", "report_path", "records", "issued_at", "number", "git_modified"}
"""Fields that differ between two runs of the same revision (wall-clock times, ids, ports, paths)."""


@contextmanager
def checkout(revision: str | None) -> Iterator[Path]:
    """A tree of `revision` (None: the working tree itself)."""
    if revision is None:
        yield ROOT
        return
    with tempfile.TemporaryDirectory(prefix="hilcal-rev-") as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), revision],
                       check=True, capture_output=True)
        try:
            yield tree
        finally:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], check=False,
                           capture_output=True)


def _hilcal(tree: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(tree), "MPLBACKEND": "Agg"}
    return subprocess.run([sys.executable, "-m", "procedures.cli", *args], cwd=tree, env=env, text=True,
                          capture_output=True, timeout=600)


def outputs(tree: Path) -> dict[str, Any]:
    """The demo run's report.json and the small hexapod's diagnosis, as produced by the code in `tree`."""
    with tempfile.TemporaryDirectory(prefix="hilcal-out-") as tmp:
        run = _hilcal(tree, "run", "--sim", "--yes", "--out", f"{tmp}/run", "--records", f"{tmp}/records.sqlite")
        if run.returncode != 0:
            raise SystemExit(f"`hilcal run --sim` failed in {tree}:\n{run.stdout}\n{run.stderr}")
        report = json.loads(Path(f"{tmp}/run/report.json").read_text())
    example = tree / "examples" / "small_hexapod"
    diag = _hilcal(tree, "diagnose", str(example / "recording.csv"), "--robot", str(example / "robot.toml"),
                   "--json")
    if diag.returncode != 0:
        raise SystemExit(f"`hilcal diagnose` failed in {tree}:\n{diag.stdout}\n{diag.stderr}")
    return {"report.json": report, "diagnose --json": json.loads(diag.stdout)}


def differences(a: Any, b: Any, where: str = "") -> list[str]:
    """Every path at which `a` and `b` differ, ignoring VOLATILE_KEYS."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in sorted(set(a) | set(b)):
            if key in VOLATILE_KEYS:
                continue
            if key not in a or key not in b:
                out.append(f"{where}/{key}: only in {'after' if key not in a else 'before'}")
            else:
                out += differences(a[key], b[key], f"{where}/{key}")
        return out
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{where}: {len(a)} items before, {len(b)} after"]
        return [d for k, (x, y) in enumerate(zip(a, b, strict=True)) for d in differences(x, y, f"{where}[{k}]")]
    return [] if a == b else [f"{where}: {str(a)[:80]!r} before, {str(b)[:80]!r} after"]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("before", help="git revision before the change, e.g. HEAD or a commit id")
    parser.add_argument("after", nargs="?", default=None, help="git revision after (default: the working tree)")
    args = parser.parse_args()
    results = []
    for revision in (args.before, args.after):
        with checkout(revision) as tree:
            print(f"running {revision or 'working tree'} in {tree} ...", flush=True)
            results.append(outputs(tree))
    diffs = differences(*results)
    for name in results[0]:
        n = sum(d.startswith(f"/{name}") for d in diffs)
        print(f"{name}: {'identical' if n == 0 else f'{n} differences'}")
    for d in diffs:
        print("  " + d)
    return 1 if diffs else 0


if __name__ == "__main__":
    raise SystemExit(main())
