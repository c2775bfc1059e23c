"""The job lifecycle log: one line per event (created, started, stage, succeeded, failed, cancelled), as
``key=value`` pairs on the ``lidarmap.jobs`` logger, e.g.::

    job event=succeeded job=1b9e... duration_s=41.2 scans=910 peak_memory_mb=612

Values with spaces or quotes are quoted (JSON string rules), so each line splits with ``shlex.split``.
"""

from __future__ import annotations

import json
import logging

logger = logging.getLogger("lidarmap.jobs")


def _value(value: object) -> str:
    if isinstance(value, float):
        value = round(value, 3)
    text = str(value)
    if text == "" or any(c.isspace() or c in "\"'=\\" for c in text):
        return json.dumps(text)
    return text


def job_event(event: str, job_id: str, level: int = logging.INFO, **fields: object) -> None:
    """Log one lifecycle event of job ``job_id`` with ``fields`` (None values left out)."""
    pairs = " ".join(f"{key}={_value(value)}" for key, value in fields.items() if value is not None)
    logger.log(level, "job event=%s job=%s%s", event, job_id, f" {pairs}" if pairs else "")
