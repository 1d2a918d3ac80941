"""The records' tables as the code reads and writes them (SQLAlchemy Core); the migrations build the same schema.

- ``runs``: one row per calibration run, with the machine's identity (robot name + serial) as an indexed column
  and the certificate columns that the ISO 9283 acceptance fills through ``Records.update_run``;
- ``run_parameters``: each run's estimated machine geometry, one row per parameter with its standard error (mm),
  what ``hilcal drift`` compares;
- ``parameter_sets``: every parameter set seen, keyed by the controller's SHA-256;
- ``uploads``: every controller upload, rollback or save, refused and failed ones too, with a unique
  ``upload_id`` so writing it twice (a retry, ``hilcal records sync``) stores it once;
- ``audit``: who did what when, written in the same transaction as the row it describes.

Times are ISO 8601 text in UTC (+00:00), as the drivers' records are, so they sort as text on both engines.
"""

from __future__ import annotations

import sqlalchemy as sa

metadata = sa.MetaData()

RUN_COLUMNS = ("started_at", "finished_at", "status", "robot_name", "plan_sha256", "operator", "out_dir",
               "estimator", "machine", "station", "machine_serial", "verdict", "certificate_number",
               "certificate_path")
"""Plain text columns of a run (verify_before/verify_after are JSON, stored in *_json columns)."""

runs = sa.Table(
    "runs", metadata,
    sa.Column("run_id", sa.Text, primary_key=True),
    sa.Column("started_at", sa.Text, nullable=False),
    sa.Column("finished_at", sa.Text),
    sa.Column("status", sa.Text, nullable=False),
    sa.Column("robot_name", sa.Text),
    sa.Column("plan_sha256", sa.Text),
    sa.Column("operator", sa.Text),
    sa.Column("out_dir", sa.Text),
    sa.Column("estimator", sa.Text),
    sa.Column("verify_before_json", sa.Text),
    sa.Column("verify_after_json", sa.Text),
    sa.Column("machine", sa.Text),
    sa.Column("station", sa.Text),
    sa.Column("machine_serial", sa.Text),
    sa.Column("verdict", sa.Text),
    sa.Column("certificate_number", sa.Text),
    sa.Column("certificate_path", sa.Text),
)

parameter_sets = sa.Table(
    "parameter_sets", metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("sha256", sa.Text, nullable=False, unique=True),
    sa.Column("created_at", sa.Text, nullable=False),
    sa.Column("source", sa.Text, nullable=False),
    sa.Column("json", sa.Text, nullable=False),
)

uploads = sa.Table(
    "uploads", metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("run_id", sa.Text, sa.ForeignKey("runs.run_id", ondelete="RESTRICT")),
    sa.Column("time", sa.Text, nullable=False),
    sa.Column("operator", sa.Text),
    sa.Column("endpoint", sa.Text),
    sa.Column("params_sha256", sa.Text),
    sa.Column("outcome", sa.Text, nullable=False),
    sa.Column("record_json", sa.Text, nullable=False),
    sa.Column("upload_id", sa.Text, nullable=False),  # unique index uploads_by_upload_id
    sa.Column("machine", sa.Text),
    sa.Column("station", sa.Text),
)

run_parameters = sa.Table(
    "run_parameters", metadata,
    sa.Column("run_id", sa.Text, sa.ForeignKey("runs.run_id", ondelete="CASCADE"), primary_key=True),
    sa.Column("name", sa.Text, primary_key=True),
    sa.Column("value_mm", sa.Double, nullable=False),
    sa.Column("std_mm", sa.Double),
)

audit = sa.Table(
    "audit", metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("time", sa.Text, nullable=False),
    sa.Column("action", sa.Text, nullable=False),
    sa.Column("subject", sa.Text, nullable=False),
    sa.Column("operator", sa.Text),
    sa.Column("station", sa.Text),
    sa.Column("machine", sa.Text),
    sa.Column("detail_json", sa.Text, nullable=False),
)
