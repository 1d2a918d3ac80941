"""Alembic's environment for the records: migrations run on the connection that ``procedures.records.migrate``
hands over (already inside its transaction and, on PostgreSQL, holding the migration lock), never from a URL in
an ini file.
"""

from __future__ import annotations

from alembic import context

connection = context.config.attributes["connection"]
context.configure(connection=connection, target_metadata=None, transactional_ddl=True)
with context.begin_transaction():
    context.run_migrations()
