"""Alembic's environment: migrations run on the connection that
:func:`service.storage.migration.upgrade_schema` passes in ``config.attributes["connection"]``,
inside that connection's open transaction (one transaction for all of them, on SQLite and
PostgreSQL alike)."""

from __future__ import annotations

from alembic import context

from service.storage.migration import compare_type
from service.storage.tables import metadata

connection = context.config.attributes.get("connection")
if connection is None:
    raise RuntimeError("the job store's migrations run through service.storage.migration.upgrade_schema "
                       "(it opens the database and passes its connection)")
context.configure(connection=connection, target_metadata=metadata, compare_type=compare_type,
                  render_as_batch=connection.dialect.name == "sqlite")  # SQLite alters a table by copying it
with context.begin_transaction():
    context.run_migrations()
