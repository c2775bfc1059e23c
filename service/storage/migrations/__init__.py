"""Alembic's migrations of the job store (``env.py``, ``versions/``), run at every start by
:func:`service.storage.migration.upgrade_schema`."""
