"""The live mapping job: follows a session's stream, stepping the SLAM filter through each chunk as
it arrives, and writes the same products as any job once the stream ends.

* **Order.** Chunks are mapped in seq order 0, 1, 2, ...; the job waits at a gap (a later chunk
  that arrived early waits for it). A chunk is taken once its file exists: the API writes it
  atomically after recording it, so the data folder is the place to watch (shared by every
  worker, local or Celery).
* **End.** The stream is finished (``POST /v1/sessions/{id}/chunks/finish``) and every chunk up to
  its ``last_seq`` was mapped: the job finishes normally. No new chunk to map for
  ``idle_timeout_s``: the job ends too and writes the products of what it mapped, with a warning
  in run.json and ``input.ended = "idle_timeout"`` (it fails when it mapped nothing).
* **While it runs.** Progress is the scans mapped so far with an unknown total; the live map
  (PNG, tiles, trajectory) is refreshed every ``snapshot_every_scans`` processed scans, as for any
  job, and also whenever the job has caught up with the stream. A cancel is noticed at the next
  progress report or poll (within about a second).
* **Same map as a whole-stream job.** The filter is seeded and configured as a regular job's, and
  it steps through the messages in the order and with the values that job would see, so a live
  job over a stream gives the trajectory and map of a regular job over the same chunks.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from service.jobs.context import JobContext, JobFailed
from service.jobs.outputs import LiveMap, job_session, write_job_products
from service.jobs.settings import engine_config
from service.storage.chunks import read_chunk_messages, stream_state_in_store
from service.storage.stream_log import (
    MESSAGE_ORDER,
    drive_log_from_messages,
    engine_message,
    lidar_from_calibration,
    vehicle_from_calibration,
)
from slam_engine.config import SlamConfig
from slam_engine.errors import LogFormatError
from slam_engine.frontend.odometry import OdometryIntegrator, odometry_source
from slam_engine.frontend.particle_filter import SlamFilter
from slam_engine.model.drive_log import DriveLog
from slam_engine.model.messages import EncoderMessage, Message, ScanMessage
from slam_engine.model.result import MapSnapshot, SlamResult
from slam_engine.progress import MAPPING_SCANS, RunProgress

POLL_S = 0.2  # how often a job that has caught up looks for the next chunk (and for a cancel)
ODOMETRY_TYPES = ("encoder", "odometry")


class LiveRun:
    """A :class:`SlamFilter` stepped through a stream's messages chunk by chunk, keeping every
    message for the final DriveLog (dead reckoning, run.json's summary, the products).

    The filter is created at the first chunk that carries odometry (encoder or odometry
    messages), whose messages pick the odometry source by the rule a whole log uses
    (:func:`~slam_engine.frontend.odometry.odometry_source`); messages before it wait and are then replayed.
    The integrator listens to the gyro from the start: until a gyro message arrives that is the
    same as ignoring it, so a stream with a gyro and one without both match a whole-log run.
    """

    def __init__(self, calibration: dict[str, Any], config: SlamConfig):
        self.calibration = calibration
        self.config = config
        self.lidar = lidar_from_calibration(calibration.get("lidar"))
        self.vehicle = vehicle_from_calibration(calibration["vehicle"])
        self.messages: list[dict[str, Any]] = []
        self.slam: SlamFilter | None = None
        self._before_odometry: list[Message] = []
        self._wheels: int | None = None

    @property
    def scans_done(self) -> int:
        """Scans taken so far (as a regular job counts them: handled, or waiting for odometry)."""
        if self.slam is None:
            return sum(isinstance(m, ScanMessage) for m in self._before_odometry)
        return self.slam.scans_seen

    def feed(self, chunk: list[dict[str, Any]], seq: int, on_scan: Callable[[], None]) -> None:
        """Step the filter through one chunk's messages; ``on_scan()`` after every scan."""
        checked = [(m, self._engine_message(m, f"chunk {seq}, message {i}")) for i, m in enumerate(chunk)]
        checked.sort(key=lambda pair: (pair[0]["t_s"], MESSAGE_ORDER[pair[0]["type"]]))  # DriveLog.messages() order
        self.messages.extend(m for m, _ in checked)
        messages = [message for _, message in checked]
        if self.slam is None:
            self._before_odometry.extend(messages)
            if not any(m["type"] in ODOMETRY_TYPES for m, _ in checked):
                return
            self.slam = self._make_filter([m for m, _ in checked])
            messages, self._before_odometry = self._before_odometry, []
        for message in messages:
            self.slam.step(message)
            if isinstance(message, ScanMessage):
                on_scan()

    def _engine_message(self, m: dict[str, Any], location: str) -> Message:
        message = engine_message(m, self.lidar, location)
        if isinstance(message, EncoderMessage):
            if self._wheels is None:
                self._wheels = len(message.ticks)
            elif len(message.ticks) != self._wheels:
                raise LogFormatError("encoder messages carry different numbers of wheels", location=location)
        return message

    def _make_filter(self, chunk: list[dict[str, Any]]) -> SlamFilter:
        odometry = drive_log_from_messages(self.calibration, [m for m in chunk if m["type"] != "scan"])
        source = odometry_source(odometry)
        if source == "encoders" and odometry.gyro is None:
            OdometryIntegrator(self.vehicle, source, use_gyro=False)  # ConfigError: no track width for the heading
        integrator = OdometryIntegrator(self.vehicle, source, use_gyro=True)
        assert self.lidar is not None  # run_live_job refuses a calibration without 'lidar'
        return SlamFilter(self.lidar, integrator, self.config)

    def latest_snapshot(self) -> MapSnapshot | None:
        """The newest of the filter's periodic snapshots (``snapshot_every_scans``)."""
        return self.slam.snapshots[-1] if self.slam is not None and self.slam.snapshots else None

    def current_snapshot(self) -> MapSnapshot | None:
        """The map and trajectory now (not kept among the run's snapshots: the animation stays that
        of a regular run)."""
        if self.slam is None:
            return None
        trajectory = self.slam.trajectory()
        if len(trajectory) == 0:
            return None
        return MapSnapshot(scan_index=len(trajectory) - 1, t_s=float(trajectory.t_s[-1]),
                           grid=self.slam.preview_grid(), trajectory=trajectory)

    def result(self, started_s: float, progress: Callable[[RunProgress], None] | None = None
               ) -> tuple[SlamResult, DriveLog]:
        """Finish the filter and collect the run's result over every message fed (``progress`` hears the
        back end's stages)."""
        from slam_engine.pipeline import filter_result, run_slam

        log = drive_log_from_messages(self.calibration, self.messages)
        if self.slam is None or log.scans is None:  # no odometry (an error) or no scans: as a regular job
            return run_slam(log, self.config), log
        self.slam.finish()
        return filter_result(self.slam, log, self.config, started_s, progress), log


class LiveTiming:
    """Where a live job's time went while it followed the stream: reading and mapping chunks (live
    snapshots left out) and writing live snapshots (PNG, tile grid, trajectory), in seconds."""

    def __init__(self) -> None:
        self.mapping_s = 0.0
        self.snapshots = 0
        self.snapshots_s = 0.0

    @contextmanager
    def mapping(self) -> Iterator[None]:
        """Time the block (a chunk read and mapped) as mapping, less the snapshots written meanwhile."""
        started, snapshots_before = time.perf_counter(), self.snapshots_s
        yield
        self.mapping_s += time.perf_counter() - started - (self.snapshots_s - snapshots_before)

    def snapshot(self, live_map: LiveMap, snapshot: Callable[[], MapSnapshot | None]) -> None:
        """``live_map.update(snapshot())``, counted and timed when it writes."""
        started = time.perf_counter()
        if live_map.update(snapshot()):
            self.snapshots += 1
            self.snapshots_s += time.perf_counter() - started

    def as_dict(self) -> dict[str, float | int]:
        return {"mapping_s": round(self.mapping_s, 3), "snapshots": self.snapshots,
                "snapshots_s": round(self.snapshots_s, 3)}


def run_live_job(ctx: JobContext) -> None:
    """Job function part for ``"live": true`` jobs (called by :func:`service.jobs.mapping.run_mapping_job`)."""
    job, session_id = ctx.job, ctx.job.session_id
    session = job_session(ctx)
    calibration = session.calibration
    if calibration is None or calibration.get("lidar") is None:
        raise JobFailed("a live job needs the session's calibration with 'lidar'")
    config = engine_config(job.config)
    idle_timeout_s = float(job.config["idle_timeout_s"])
    started_s = time.perf_counter()
    ctx.store.set_input(ctx.job_id, {"source": "stream", "live": True, "ended": None})
    run = LiveRun(calibration, config)
    live_map = LiveMap(ctx.data.live_dir(ctx.job_id))
    timing = LiveTiming()

    def on_scan() -> None:
        ctx.progress(run.scans_done, None, stage=MAPPING_SCANS)
        timing.snapshot(live_map, run.latest_snapshot)

    seq, published, last_seq = 0, -1, None
    idle_since = time.monotonic()
    while True:
        if ctx.data.chunk_file(session_id, seq).exists():
            with timing.mapping():
                run.feed(read_chunk_messages(ctx.data, session_id, seq), seq, on_scan)
            seq += 1
            idle_since = time.monotonic()
            continue
        last_seq = ctx.store.stream_end(session_id)
        if last_seq is not None and seq > last_seq:
            ended = "finished"
            break
        # caught up with the stream: show the map so far, record progress (raises Cancelled when asked)
        if config.snapshot_every_scans and run.scans_done != published:
            timing.snapshot(live_map, run.current_snapshot)
            published = run.scans_done
        ctx.progress(run.scans_done, None, force=True, stage=MAPPING_SCANS)
        if time.monotonic() - idle_since >= idle_timeout_s:
            ended = "idle_timeout"
            break
        time.sleep(POLL_S)

    if not run.messages:
        raise JobFailed(f"live stream idle: no chunk arrived within idle_timeout_s ({idle_timeout_s:g} s), "
                        "nothing to map")
    result, log = run.result(started_s, ctx.run_progress)
    description: dict[str, Any] = {"source": "stream", "live": True, "ended": ended, "chunks_used": seq,
                                   "messages": len(run.messages), "last_seq": last_seq,
                                   "live_timing": timing.as_dict()}
    if ended == "idle_timeout":
        state = stream_state_in_store(ctx.store, session_id)
        description["missing_seqs_after"] = state.missing_seqs
        waiting = (f"chunk {seq} never arrived (the stream ends at seq {last_seq})" if last_seq is not None
                   else "the stream was not finished")
        result.warnings.append(f"no new chunk for idle_timeout_s ({idle_timeout_s:g} s): mapped chunks 0..{seq - 1}; "
                               f"{waiting}")
    ctx.store.set_input(ctx.job_id, {**description, "summary": log.summary()})
    write_job_products(ctx, result, log)
