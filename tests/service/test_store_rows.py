"""The job store hands out typed rows (service/storage/rows.py), and the service names job statuses
only through the JobStatus enum."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest

from api_schemas.jobs import JobSource, JobStatus
from service.storage.rows import ChunkRow, JobRow, LogRow, SessionRow, StreamFigures
from service.storage.store import JobStore

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def store(tmp_path: Path) -> JobStore:
    store = JobStore(tmp_path / "jobs.sqlite3")
    store.initialise()
    return store


def test_every_read_returns_a_typed_row(store: JobStore) -> None:
    session = store.create_session("alice", "drive", None, {"vehicle": {"wheel_radius_m": 0.1}}, None)
    assert isinstance(session, SessionRow) and session.calibration == {"vehicle": {"wheel_radius_m": 0.1}}
    log = store.add_log("log-1", session.id, "a.clf", 10, "aa", True, {"format": "carmen"}, "uploads/log-1/tree")
    assert isinstance(log, LogRow) and log.archive is True and log.summary == {"format": "carmen"}
    assert store.list_logs(session.id) == [log] and store.get_log("log-1", session.id) == log
    chunk = store.put_chunk(session.id, 0, "h0", 3, 0.0, 0.5).row
    assert isinstance(chunk, ChunkRow) and (chunk.seq, chunk.messages, chunk.t_last_s) == (0, 3, 0.5)
    assert store.chunk_rows(session.id) == [chunk] and store.chunk_rows_near(session.id, 1) == [chunk]
    figures = store.stream_figures(session.id)
    assert figures == StreamFigures(received=1, contiguous_through=0, messages=3, highest=0, after=[], last_seq=None)

    job = store.create_job(session.id, "alice", JobSource.LOG, "log-1", {"particles": 4, "live": False})
    assert isinstance(job, JobRow) and type(job.status) is JobStatus and type(job.source) is JobSource
    assert (job.status, job.source, job.config["particles"], job.live, job.active) == (
        JobStatus.QUEUED, JobSource.LOG, 4, False, True)
    assert store.mark_running(job.id, worker_pid=7)
    store.set_products(job.id, {"run.json": "products/run.json"})
    assert store.finish(job.id, JobStatus.SUCCEEDED)
    done = store.get_job(job.id)
    assert done is not None and done.status is JobStatus.SUCCEEDED and not done.active
    assert (done.progress, done.worker_pid, done.products) == (1.0, 7, {"run.json": "products/run.json"})
    rows, count = store.list_jobs("alice", session.id, JobStatus.SUCCEEDED, 10, 0)
    assert rows == [done] and count == 1
    live, active = store.create_live_job(session.id, "alice", {"live": True})
    assert live is not None and active is None and live.live and live.source is JobSource.STREAM
    assert store.request_cancel(live.id) is JobStatus.CANCELLED and store.request_cancel("nothing") is None


def test_rows_are_snapshots_and_finish_takes_only_terminal_statuses(store: JobStore) -> None:
    sid = store.create_session("", "s", None, None, None).id
    job = store.create_job(sid, "", JobSource.STREAM, None, {})
    with pytest.raises(dataclasses.FrozenInstanceError):
        job.status = JobStatus.RUNNING  # type: ignore[misc]
    with pytest.raises(ValueError, match="finishes as one of"):
        store.finish(job.id, JobStatus.RUNNING)
    assert store.get_job(job.id) == job  # nothing changed


def test_the_service_spells_no_status_as_a_string() -> None:
    """A status compared or stored as a bare string ("running") would pass the type checker; the
    enum is the one spelling (prose in docstrings and messages is longer than a bare status)."""
    statuses = {status.value for status in JobStatus}
    found = []
    for path in sorted((ROOT / "service").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Constant) and node.value in statuses:
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {node.value!r}")
    assert found == []
