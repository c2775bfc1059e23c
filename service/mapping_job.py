"""The mapping job, run in a worker process: load the input, run SLAM with progress, cancel and
live snapshots, then write the products.

Input: an uploaded log (loaded again with ``load_log``), the session's streamed chunks 0..k that
are contiguous when the job starts, or - a live job (``"live": true``) - the session's chunks
followed in seq order as they arrive until the stream is finished or idle
(:mod:`service.live_job`). Every kind writes the same products (:func:`write_job_products`).
"""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from service.chunks import read_chunk_messages, stream_state
from service.job_estimate import check_job_memory
from service.job_settings import engine_config
from service.products import COMPILING_FILE, GRID_FILE, TEXTURE_FILE, save_grid, save_texture
from service.storage import write_atomic
from service.stream_log import drive_log_from_messages
from service.worker import JobContext
from slam_engine.config import SlamConfig
from slam_engine.drive_log import DriveLog
from slam_engine.errors import LogFormatError
from slam_engine.products import write_trajectory_json
from slam_engine.products.rendering import occupancy_image, png_bytes


def slam_config(job_config: dict[str, Any]) -> SlamConfig:
    """The engine configuration a stored job runs with (:mod:`service.job_settings`)."""
    return engine_config(job_config)


def load_input(ctx: JobContext) -> tuple[DriveLog, dict[str, Any]]:
    """The job's DriveLog and a description of what it is (stored with the job)."""
    job = ctx.job
    store, data = ctx.store, ctx.data
    session = session_row(ctx)
    if job["source"] == "log":
        from slam_engine.formats import load_log

        log_row = store.get_log(job["log_id"], job["session_id"])
        if log_row is None:
            raise LogFormatError("the job's log was deleted")
        path = data.resolve(log_row["stored_path"])
        log = load_log(path, format=stored_log_format(path, log_row["summary"].get("format", "auto")))
        return log, {"source": "log", "log_id": log_row["id"], "sha256": log_row["sha256"], "summary": log.summary()}
    rows = store.chunk_rows(job["session_id"])
    state = stream_state(rows)
    if state.contiguous_through < 0:
        raise LogFormatError("no contiguous chunks from seq 0", location="chunk 0")
    messages: list[dict[str, Any]] = []
    for seq in range(state.contiguous_through + 1):
        ctx.check_cancel()
        messages.extend(read_chunk_messages(data, job["session_id"], seq))
    log = drive_log_from_messages(session["calibration"], messages)
    return log, {"source": "stream", "chunks_used": state.contiguous_through + 1,
                 "messages": len(messages), "missing_seqs_after": state.missing_seqs, "summary": log.summary()}


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


def session_row(ctx: JobContext) -> dict[str, Any]:
    session = ctx.store.get_session(ctx.job["session_id"], ctx.job["owner"])
    if session is None:
        raise LogFormatError("the job's session was deleted")
    return session


class LiveMap:
    """Writes the map so far (PNG and the tile grid) whenever the run hands over a new snapshot;
    files are replaced atomically, so readers never see half a file."""

    def __init__(self, live_dir: Path):
        self.live_dir = live_dir
        self._last_scan_index: int | None = None

    def update(self, snapshot: Any) -> None:
        if snapshot is None or snapshot.scan_index == self._last_scan_index:
            return
        self._last_scan_index = snapshot.scan_index
        self.live_dir.mkdir(parents=True, exist_ok=True)
        save_grid(snapshot.grid, self.live_dir / GRID_FILE)
        write_atomic(self.live_dir / "occupancy.png", png_bytes(occupancy_image(snapshot.grid)))
        write_trajectory_json(snapshot.trajectory, self.live_dir / "trajectory.json", frame="map (so far)")


@contextlib.contextmanager
def compiling_status(ctx: JobContext) -> Iterator[None]:
    """Within the block, the job's status says 'compiling' while the engine compiles a kernel (a
    marker file in its live folder, :func:`service.products.engine_compiling`)."""
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
    if ctx.job["config"].get("live"):
        from service.live_job import run_live_job

        run_live_job(ctx)
        return
    from slam_engine.pipeline import run_slam

    log, description = load_input(ctx)
    ctx.store.set_input(ctx.job_id, description)
    if ctx.memory is not None:  # streamed input: its scan count (and so its frames) is known only now
        check_job_memory(ctx.job["config"], len(log.scans) if log.scans is not None else 0, ctx.memory.limit_mb)
    config = slam_config(ctx.job["config"])
    live = LiveMap(ctx.data.live_dir(ctx.job_id))

    def on_progress(progress: Any) -> None:
        ctx.progress(progress.scans_done, progress.scans_total)
        live.update(progress.latest_snapshot)

    result = run_slam(log, config, rng=np.random.default_rng(config.seed), progress=on_progress)
    total = len(log.scans) if log.scans is not None else 0
    ctx.progress(total, total, force=True)
    write_job_products(ctx, result, log)


def write_job_products(ctx: JobContext, result: Any, log: DriveLog) -> None:
    """Write a finished run's products into the job's folder, list them in the store, drop the live
    snapshot."""
    from slam_engine.products import GeoOrigin, write_products, write_trajectory_tum

    peak = ctx.peak_memory_bytes()
    if peak:  # this job's own peak (the engine's getrusage figure spans the worker's whole life)
        result.peak_memory_bytes = peak
    out_dir = ctx.out_dir
    session = session_row(ctx)
    geo = None if session["geo"] is None else GeoOrigin(
        latitude_deg=session["geo"]["lat_deg"], longitude_deg=session["geo"]["lon_deg"],
        heading_deg=session["geo"]["heading_deg"])
    files = write_products(result, out_dir / "products", geo=geo, log=log)
    files["dead_reckoning.tum"] = write_trajectory_tum(result.dead_reckoning,
                                                       out_dir / "products" / "dead_reckoning.tum")
    save_grid(result.grid, out_dir / GRID_FILE)
    if result.texture is not None:
        save_texture(result.texture, out_dir / TEXTURE_FILE)
    ctx.store.set_products(ctx.job_id, product_names(files, out_dir))
    shutil.rmtree(ctx.data.live_dir(ctx.job_id), ignore_errors=True)


def product_names(files: dict[str, Path], out_dir: Path) -> dict[str, str]:
    """API product name -> file path relative to the job folder, for the files write_products made."""
    return {Path(path).name: str(Path(path).resolve().relative_to(out_dir.resolve())) for path in files.values()}
