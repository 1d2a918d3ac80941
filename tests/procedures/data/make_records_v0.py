"""Writes records_v0.sqlite: a records file made by the SQLite-only records layer (schema version 1).

The in-place migration to the SQLAlchemy/Alembic schema is tested on this file. The script loads
``procedures/records.py`` as it was at commit bda3cdc (before the records moved to SQLAlchemy) with
``git show``, and writes runs, parameter sets and uploads through that module's own API, so the file is
exactly what a station's ``runs/records.sqlite`` looked like. Run from the repository root:

    .venv/bin/python tests/procedures/data/make_records_v0.py
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tempfile
from pathlib import Path
from types import ModuleType

V0_COMMIT = "bda3cdc06d0c244f82f23fe1155bfbcfbdfc042a"
HERE = Path(__file__).resolve().parent
OUT = HERE / "records_v0.sqlite"


def old_records_module() -> ModuleType:
    """procedures/records.py at V0_COMMIT, imported under another name."""
    source = subprocess.run(["git", "show", f"{V0_COMMIT}:procedures/records.py"], check=True, capture_output=True,
                            text=True, cwd=HERE).stdout
    path = Path(tempfile.mkdtemp()) / "records_v0.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("records_v0", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["records_v0"] = module
    spec.loader.exec_module(module)
    return module


def params(offset_mm: float) -> dict[str, list]:
    """A parameter set near the paper robot's shape (values only need to be a sane set)."""
    a = [[600.0 + offset_mm, 100.0 * i, 0.0] for i in range(6)]
    b = [[400.0, 80.0 * i + offset_mm, 0.0] for i in range(6)]
    return {"a_mm": a, "b_mm": b, "l0_mm": [1000.0 + offset_mm] * 6}


def main() -> None:
    old = old_records_module()
    OUT.unlink(missing_ok=True)
    before = {"max_position_mm": 6.9595, "rms_position_mm": 6.1455, "max_orientation_deg": 0.6977,
              "rms_orientation_deg": 0.5971}
    after = {"max_position_mm": 0.0412, "rms_position_mm": 0.0217, "max_orientation_deg": 0.0031,
             "rms_orientation_deg": 0.0018}
    with old.Records(OUT) as db:
        db.record_run("20260301T080000Z-aaaaaa", started_at="2026-03-01T08:00:00+00:00", status="running",
                      robot_name="paper-table1", plan_sha256="1" * 64, operator="J. Smith",
                      out_dir="/data/runs/r1", estimator="ls")
        db.update_run("20260301T080000Z-aaaaaa", status="complete", finished_at="2026-03-01T08:41:00+00:00",
                      verify_before=before, verify_after=after)
        sha = db.add_parameter_set(params(0.1), "identified")
        db.add_parameter_set(params(0.0), "controller")
        db.record_upload({"operation": "upload", "outcome": "committed", "endpoint": "tcp://127.0.0.1:1502",
                          "device_id": 1, "started_at": "2026-03-01T08:30:00+00:00",
                          "finished_at": "2026-03-01T08:30:02+00:00", "params_sha256": sha,
                          "live_readback_match": True}, "J. Smith", run_id="20260301T080000Z-aaaaaa")
        db.record_run("20260302T090000Z-bbbbbb", started_at="2026-03-02T09:00:00+00:00", status="running",
                      robot_name="paper-table1", plan_sha256="2" * 64, operator="K. Lee", out_dir="/data/runs/r2",
                      estimator="linf")
        db.update_run("20260302T090000Z-bbbbbb", status="interrupted", verify_before=before)
        db.record_upload({"operation": "upload", "outcome": "refused", "endpoint": "tcp://127.0.0.1:1502",
                          "started_at": "2026-03-02T09:20:00+00:00", "finished_at": "2026-03-02T09:20:00+00:00",
                          "error": "NotDisabled: controller is ENABLED"}, "K. Lee", run_id="20260302T090000Z-bbbbbb")
        db.add_parameter_set({"leg1_dl0_mm": 0.5}, "file")
        db.record_upload({"operation": "rollback", "outcome": "rolled_back", "endpoint": "tcp://127.0.0.1:1502",
                          "started_at": "2026-03-03T10:00:00+00:00", "finished_at": "2026-03-03T10:00:01+00:00",
                          "params_sha256": "f" * 64}, "bob")
        db.record_run("20260304T070000Z-cccccc", started_at="2026-03-04T07:00:00+00:00", status="running",
                      robot_name="hexapod-small", operator=None, out_dir="/data/runs/r3", estimator="ls")
    print(f"wrote {OUT} ({OUT.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
