"""Machine identity, certificates, per-run parameters, unique upload ids and the audit trail.

Runs get the machine's identity (robot name + serial; runs recorded before this revision have no serial, so their
identity is their robot name), the station, and the ISO 9283 certificate columns. Uploads get a unique
``upload_id`` (older rows: ``legacy-<row id>``) and the machine. New tables: ``run_parameters`` (each run's
estimated geometry with standard errors, for drift) and ``audit``.

Revision ID: 0002
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0002"
down_revision = "0001"
branch_labels = None
depends_on = None

SQLITE_USER_VERSION = 2
"""Set on SQLite files, so the SQLite-only records layer (which knew version 1) refuses them clearly."""
NEW_RUN_COLUMNS = ("machine", "station", "machine_serial", "verdict", "certificate_number", "certificate_path")


def upgrade() -> None:
    for name in NEW_RUN_COLUMNS:
        op.add_column("runs", sa.Column(name, sa.Text))
    op.execute("UPDATE runs SET machine = robot_name WHERE machine IS NULL")
    op.create_index("runs_by_machine_start", "runs", ["machine", "started_at"])
    op.add_column("uploads", sa.Column("upload_id", sa.Text))
    op.add_column("uploads", sa.Column("machine", sa.Text))
    op.add_column("uploads", sa.Column("station", sa.Text))
    op.execute("UPDATE uploads SET upload_id = 'legacy-' || CAST(id AS VARCHAR) WHERE upload_id IS NULL")
    op.execute("UPDATE uploads SET machine = (SELECT runs.machine FROM runs WHERE runs.run_id = uploads.run_id) "
               "WHERE run_id IS NOT NULL")
    with op.batch_alter_table("uploads", copy_from=_uploads_before_not_null(),
                              table_kwargs={"sqlite_autoincrement": True}) as batch:
        batch.alter_column("upload_id", existing_type=sa.Text, nullable=False)
    op.create_index("uploads_by_upload_id", "uploads", ["upload_id"], unique=True)
    op.create_index("uploads_by_machine_time", "uploads", ["machine", "time"])
    op.create_table(
        "run_parameters",
        sa.Column("run_id", sa.Text, sa.ForeignKey("runs.run_id", ondelete="CASCADE"), primary_key=True),
        sa.Column("name", sa.Text, primary_key=True),
        sa.Column("value_mm", sa.Double, nullable=False),
        sa.Column("std_mm", sa.Double),
    )
    op.create_table(
        "audit",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("time", sa.Text, nullable=False),
        sa.Column("action", sa.Text, nullable=False),
        sa.Column("subject", sa.Text, nullable=False),
        sa.Column("operator", sa.Text),
        sa.Column("station", sa.Text),
        sa.Column("machine", sa.Text),
        sa.Column("detail_json", sa.Text, nullable=False),
        sqlite_autoincrement=True,
    )
    op.create_index("audit_by_subject", "audit", ["subject"])
    if op.get_context().dialect.name == "sqlite":
        op.execute(f"PRAGMA user_version = {SQLITE_USER_VERSION}")


def _uploads_before_not_null() -> sa.Table:
    """The uploads table as it stands before upload_id becomes NOT NULL (SQLite copies it from this, so the
    foreign key keeps its ON DELETE RESTRICT, which reflection would drop)."""
    return sa.Table(
        "uploads", sa.MetaData(),
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("run_id", sa.Text, sa.ForeignKey("runs.run_id", ondelete="RESTRICT")),
        sa.Column("time", sa.Text, nullable=False),
        sa.Column("operator", sa.Text),
        sa.Column("endpoint", sa.Text),
        sa.Column("params_sha256", sa.Text),
        sa.Column("outcome", sa.Text, nullable=False),
        sa.Column("record_json", sa.Text, nullable=False),
        sa.Column("upload_id", sa.Text),
        sa.Column("machine", sa.Text),
        sa.Column("station", sa.Text),
        sa.Index("uploads_by_run", "run_id"),
        sa.Index("uploads_by_endpoint_time", "endpoint", "time"),
    )


def downgrade() -> None:
    op.drop_table("audit")
    op.drop_table("run_parameters")
    op.drop_index("uploads_by_machine_time", "uploads")
    op.drop_index("uploads_by_upload_id", "uploads")
    with op.batch_alter_table("uploads") as batch:
        for name in ("station", "machine", "upload_id"):
            batch.drop_column(name)
    op.drop_index("runs_by_machine_start", "runs")
    with op.batch_alter_table("runs") as batch:
        for name in reversed(NEW_RUN_COLUMNS):
            batch.drop_column(name)
