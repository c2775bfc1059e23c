"""The job store's schema brought up to date at every start, with Alembic (revisions in
``service/storage/migrations/versions``).

:func:`upgrade_schema` runs on an open transaction that the caller has made exclusive (SQLite's
``BEGIN IMMEDIATE``, PostgreSQL's advisory lock), so a process that starts while another migrates
waits, then finds the schema at head. A database made before migrations (tables, no
``alembic_version``) is migrated from the start: the initial revision adds only what it lacks.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from alembic import command
from alembic.config import Config
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Connection, Float

MIGRATIONS = Path(__file__).resolve().parent / "migrations"
logger = logging.getLogger(__name__)


def alembic_config(connection: Connection | None = None) -> Config:
    """Alembic's configuration for the store's migrations (on ``connection`` when given)."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    config.attributes["connection"] = connection
    return config


def head_revision() -> str:
    """The newest revision."""
    head = ScriptDirectory.from_config(alembic_config()).get_current_head()
    if head is None:
        raise RuntimeError(f"no migrations in {MIGRATIONS}")
    return head


def current_revision(connection: Connection) -> str | None:
    """The revision the database is at (None: a new database, or one made before migrations)."""
    return MigrationContext.configure(connection).get_current_revision()


def compare_type(context: Any, inspected_column: Any, metadata_column: Any, inspected_type: Any,
                 metadata_type: Any) -> bool | None:
    """Autogenerate's type comparison, except that SQLite's REAL (what it reports for DOUBLE
    PRECISION: an 8-byte float either way) equals DOUBLE PRECISION; None: Alembic's default."""
    if context.dialect.name == "sqlite" and isinstance(inspected_type, Float) and isinstance(metadata_type, Float):
        return False
    return None


def upgrade_schema(connection: Connection) -> None:
    """Bring the database to the newest revision."""
    before, head = current_revision(connection), head_revision()
    if before != head:
        command.upgrade(alembic_config(connection), "head")
        logger.info("job store schema migrated from revision %s to %s", before or "none", head)
