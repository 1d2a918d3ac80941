"""The records as the SQLite-only records layer wrote them (its schema version 1): runs, parameter sets, uploads.

An existing file of that layer is stamped at this revision (its tables are already there) and upgraded from here.

Revision ID: 0001
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

revision = "0001"
down_revision = None
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "runs",
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
    )
    op.create_table(
        "parameter_sets",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("sha256", sa.Text, nullable=False, unique=True),
        sa.Column("created_at", sa.Text, nullable=False),
        sa.Column("source", sa.Text, sa.CheckConstraint("source IN ('identified', 'controller', 'file')"),
                  nullable=False),
        sa.Column("json", sa.Text, nullable=False),
        sqlite_autoincrement=True,
    )
    op.create_table(
        "uploads",
        sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
        sa.Column("run_id", sa.Text, sa.ForeignKey("runs.run_id", ondelete="RESTRICT")),
        sa.Column("time", sa.Text, nullable=False),
        sa.Column("operator", sa.Text),
        sa.Column("endpoint", sa.Text),
        sa.Column("params_sha256", sa.Text),
        sa.Column("outcome", sa.Text, nullable=False),
        sa.Column("record_json", sa.Text, nullable=False),
        sqlite_autoincrement=True,
    )
    op.create_index("uploads_by_run", "uploads", ["run_id"])
    op.create_index("uploads_by_endpoint_time", "uploads", ["endpoint", "time"])
    op.create_index("runs_by_start", "runs", ["started_at"])


def downgrade() -> None:
    for table in ("uploads", "parameter_sets", "runs"):
        op.drop_table(table)
