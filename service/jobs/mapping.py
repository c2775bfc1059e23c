"""The mapping job, run in a worker process: load the input, run SLAM with progress, cancel and
live snapshots, then write the products.

Input: an uploaded log (loaded again with ``load_log``), the session's streamed chunks 0..k that
are contiguous when the job starts, or - a live job (``"live": true``) - the session's chunks
followed in seq order as they arrive until the stream is finished or idle
(:mod:`service.jobs.live`). Every kind writes the same products
(:func:`service.jobs.outputs.write_job_products`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from api_schemas.jobs import JobMode, JobSource
from service.jobs.context import JobContext
from service.jobs.estimate import ExtentGuard, check_drive_memory, check_job_memory
from service.jobs.live import run_live_job
from service.jobs.outputs import LiveMap, job_session, write_job_products
from service.jobs.products import COMPILING_FILE
from service.jobs.saved_maps import job_mode, run_from_saved_map, run_merge_job
from service.jobs.settings import engine_config
from service.storage.chunks import read_chunk_messages, stream_state
from service.storage.stream_log import drive_log_from_messages
from slam_engine.errors import LogFormatError
from slam_engine.model.drive_log import DriveLog


def load_input(ctx: JobContext) -> tuple[DriveLog, dict[str, Any]]:
    """The job's DriveLog and a description of what it is (stored with the job)."""
    job = ctx.job
    store, data = ctx.store, ctx.data
    session = job_session(ctx)
    if job.source is JobSource.LOG:
        from slam_engine.formats import load_log

        log_row = None if job.log_id is None else store.get_log(job.log_id, job.session_id)
        if log_row is None:
            raise LogFormatError("the job's log was deleted")
        path = data.resolve(log_row.stored_path)
        log = load_log(path, format=stored_log_format(path, log_row.summary.get("format", "auto")))
        name_as_uploaded(log, path, log_row.filename)
        return log, {"source": "log", "log_id": log_row.id, "sha256": log_row.sha256, "summary": log.summary()}
    rows = store.chunk_rows(job.session_id)
    state = stream_state(rows)
    if state.contiguous_through < 0:
        raise LogFormatError("no contiguous chunks from seq 0", location="chunk 0")
    messages: list[dict[str, Any]] = []
    for seq in range(state.contiguous_through + 1):
        ctx.check_cancel()
        messages.extend(read_chunk_messages(data, job.session_id, seq))
    if session.calibration is None:
        raise LogFormatError("streamed chunks need the session's calibration")
    log = drive_log_from_messages(session.calibration, messages)
    return log, {"source": "stream", "chunks_used": state.contiguous_through + 1,
                 "messages": len(messages), "missing_seqs_after": state.missing_seqs, "summary": log.summary()}


def name_as_uploaded(log: DriveLog, path: Path, filename: str) -> None:
    """The log's warnings (kept in the job's input and run.json) name the upload as its user did
    (``filename``), not by the server's path; a file inside an uploaded folder by its path there."""
    folder = f"{path.parent}/"
    log.warnings[:] = [warning.replace(str(path), filename).replace(folder, "") for warning in log.warnings]


def stored_log_format(path: Path, checked_as: str) -> str:
    """The format to load an uploaded log with: the one its upload was checked as (an explicit
    ``?format=`` may name one that detection misses), or "auto" where detection agrees (detection
    also finds the log inside a zipped folder)."""
    from slam_engine.errors import SlamEngineError
    from slam_engine.formats import detect_format

    try:
        return "auto" if detect_format(path) == checked_as else checked_as
    except SlamEngineError:
        return checked_as


@contextlib.contextmanager
def compiling_status(ctx: JobContext) -> Iterator[None]:
    """Within the block, the job's status says 'compiling' while the engine compiles a kernel (a
    marker file in its live folder, :func:`service.jobs.products.engine_compiling`)."""
    from slam_engine.kernels import compile_notices

    marker = ctx.data.live_dir(ctx.job_id) / COMPILING_FILE

    def on_compiling(compiling: bool) -> None:
        if compiling:
            marker.parent.mkdir(parents=True, exist_ok=True)
            marker.touch()
        else:
            marker.unlink(missing_ok=True)

    try:
        with compile_notices(on_compiling):
            yield
    finally:
        marker.unlink(missing_ok=True)


def run_mapping_job(ctx: JobContext) -> None:
    """Job function for the worker: input -> run_slam -> products (names as the API serves them).
    While the engine compiles a kernel (no warm cache), the job's status says so."""
    with compiling_status(ctx):
        _run_mapping_job(ctx)


def _run_mapping_job(ctx: JobContext) -> None:
    if ctx.job.live and job_mode(ctx.job.config) is JobMode.LOCALIZE:
        from service.jobs.live_localization import run_live_localization_job

        run_live_localization_job(ctx)
        return
    if ctx.job.live:
        run_live_job(ctx)
        return
    if job_mode(ctx.job.config) is JobMode.MERGE:  # two saved maps, no drive to read
        run_merge_job(ctx)
        return
    from slam_engine.pipeline import run_slam

    log, description = load_input(ctx)
    ctx.store.set_input(ctx.job_id, description)
    config = engine_config(ctx.job.config)
    extent = None
    if ctx.memory is not None:  # streamed input: its scan count and extent are known only now
        from slam_engine.evaluation.memory_estimate import drive_figures

        scans = len(log.scans) if log.scans is not None else 0
        figures = drive_figures(log)
        check_job_memory(config, scans, ctx.memory.limit_mb)
        check_drive_memory(config, figures, scans, ctx.memory.limit_mb)
        extent = ExtentGuard(config, figures, scans, ctx.memory.limit_mb)
    live = LiveMap(ctx.data.live_dir(ctx.job_id))

    def on_progress(progress: Any) -> None:
        ctx.run_progress(progress)
        snapshot = progress.latest_snapshot
        live.update(snapshot)
        if extent is not None and snapshot is not None:
            extent.check(snapshot.scan_index, snapshot.trajectory.poses)

    if job_mode(ctx.job.config) is not JobMode.MAP:
        run_from_saved_map(ctx, log, on_progress)
        return
    result = run_slam(log, config, progress=on_progress)
    write_job_products(ctx, result, log)
