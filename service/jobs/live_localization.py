"""The live localisation job: a session's stream localised in a saved map while the robot drives.

A ``live`` job of mode ``localize`` follows the session's stream as a live mapping job does (chunks in
seq order, waiting at a gap; the stream's end or ``idle_timeout_s`` without a chunk ends it) and hands
each scan to a :class:`~slam_engine.multisession.live_localization.LiveLocalizer` as soon as the
odometry has reached its stamp. Until it is ready (the saved map read and its index built) the job's stage
is ``loading the map``, then ``localising scans``; chunks that came meanwhile wait. Every scan's report
(map pose, confidence, state: searching, found, carried, outside, lost) is appended to ``poses.jsonl`` in
the job's live folder with the chunk's ``seq`` and its latency (from the chunk accepted, or the job ready
when that came later, to the pose written), which ``GET /v1/jobs/{id}/poses`` serves and streams
(server-sent events). When the stream ends the search still running is waited for: a placement it
delivers reports the last scan again (found). Then the job writes a localisation's products (the poses it
reported, each scan's latest report; confidence, run.json with the live summary, the drive over the map)
and ``poses.jsonl`` among them.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections import deque
from pathlib import Path
from typing import Any

from api_schemas import LOADING_MAP_STAGE
from service.jobs.context import JobContext, JobFailed
from service.jobs.outputs import job_session, product_names
from service.jobs.settings import engine_config
from service.storage.chunks import read_chunk_messages
from service.storage.stream_log import (
    MESSAGE_ORDER,
    drive_log_from_messages,
    engine_message,
    lidar_from_calibration,
    vehicle_from_calibration,
)
from slam_engine.model.messages import ScanMessage

POSES_FILE = "poses.jsonl"  # one live report per line, in scan order
LOADING_MAP = LOADING_MAP_STAGE  # the job's stage until it is ready: the saved map read, its index built
LOCALIZING_SCANS = "localising scans"  # the job's stage while it follows the stream
POLL_S = 0.01  # how often a job that has caught up looks for the next chunk [s]: each scan's pose waits for it
STORE_POLL_S = 0.2  # ... and for the stream's end and a cancel, in the store [s]
# a chunk's last scans, stamped after its last odometry, are placed with that odometry (not the next chunk's)
# when they are at most this much newer [s]: their own matching to the drive's scans corrects the rest
EXTRAPOLATE_S = 0.25
ODOMETRY_TYPES = ("encoder", "odometry")


class LiveLocalizationRun:
    """A stream's messages, chunk by chunk, paired scan to odometry and localised scan by scan."""

    def __init__(self, calibration: dict[str, Any], config: Any, bundle: Any, threads: int):
        from slam_engine.frontend.particle_filter import make_projector
        from slam_engine.multisession.live_localization import LiveLocalizer

        self.calibration = calibration
        self.lidar = lidar_from_calibration(calibration.get("lidar"))
        self.vehicle = vehicle_from_calibration(calibration["vehicle"])
        assert self.lidar is not None  # the job refuses a calibration without 'lidar'
        self.projector = make_projector(self.lidar, config, no_return_bounded=False)
        self.localizer = LiveLocalizer(bundle, config, threads)
        self.integrator: Any = None
        self.pending: deque[ScanMessage] = deque()
        self.messages = 0

    def feed(self, chunk: list[dict[str, Any]], seq: int) -> list[Any]:
        """One chunk's messages in time order; the reports of the scans it placed."""
        checked = [(m, engine_message(m, self.lidar, f"chunk {seq}, message {i}")) for i, m in enumerate(chunk)]
        checked.sort(key=lambda pair: (pair[0]["t_s"], MESSAGE_ORDER[pair[0]["type"]]))
        self.messages += len(checked)
        if self.integrator is None and any(m["type"] in ODOMETRY_TYPES for m, _ in checked):
            self.integrator = self._integrator([m for m, _ in checked if m["type"] != "scan"])
        reports: list[Any] = []
        for _, message in checked:
            if isinstance(message, ScanMessage):
                self.pending.append(message)
            elif self.integrator is not None:
                self.integrator.update(message)
            reports += self._ready()
        return reports + self._ready(within_s=EXTRAPOLATE_S)  # the chunk's last scans: not a chunk later

    def finish(self) -> tuple[list[Any], Any]:
        """The scans still waiting for odometry, placed with the last odometry pose; then the running search
        waited for: when it placed the drive, the last scan's report again (found; else None)."""
        reports = self._ready(final=True)
        return reports, self.localizer.wait()

    def _integrator(self, messages: list[dict[str, Any]]) -> Any:
        from slam_engine.frontend.odometry import OdometryIntegrator, odometry_source

        source = odometry_source(drive_log_from_messages(self.calibration, messages))
        return OdometryIntegrator(self.vehicle, source, use_gyro=True)

    def _ready(self, final: bool = False, within_s: float = 0.0) -> list[Any]:
        """Reports of the pending scans the odometry has reached, or comes within ``within_s`` of (all of
        them when ``final``)."""
        out = []
        integrator = self.integrator
        while self.pending and integrator is not None and integrator.t_s is not None and (
                final or integrator.t_s + within_s >= self.pending[0].t_s):
            scan = self.pending.popleft()
            hits = self.projector.project(scan.ranges_m, angle_offset_rad=float(scan.angle_offset_rad)).hits_v
            out.append(self.localizer.add(scan.t_s, integrator.pose_at(scan.t_s), hits))
        return out


def run_live_localization_job(ctx: JobContext) -> None:
    """Job function part for ``"live": true, "mode": "localize"`` jobs (module docstring)."""
    from service.jobs.saved_maps import saved_map_path
    from slam_engine.errors import MapBundleError
    from slam_engine.frontend.particle_filter import engine_threads
    from slam_engine.products.map_bundle import read_bundle

    job, session_id = ctx.job, ctx.job.session_id
    ctx.progress(0, None, force=True, stage=LOADING_MAP)
    calibration = job_session(ctx).calibration
    if calibration is None or calibration.get("lidar") is None:
        raise JobFailed("a live job needs the session's calibration with 'lidar'")
    config = engine_config(job.config)
    try:
        bundle = read_bundle(saved_map_path(ctx.store, ctx.data, job.owner, str(job.config["map_job_id"])))
    except Exception as error:  # the saved map's job was deleted after this job was queued
        raise MapBundleError(str(error)) from None
    idle_timeout_s = float(job.config["idle_timeout_s"])
    ctx.store.set_input(ctx.job_id, {"source": "stream", "live": True, "ended": None,
                                     "map_job_id": job.config["map_job_id"]})
    run = LiveLocalizationRun(calibration, config, bundle, engine_threads())  # the map's index: the slow part
    ready_s = time.time()  # chunks accepted before wait for the job: their latency counts from here
    ctx.progress(0, None, force=True, stage=LOCALIZING_SCANS)
    live_dir = ctx.data.live_dir(ctx.job_id)
    live_dir.mkdir(parents=True, exist_ok=True)
    poses_path = live_dir / POSES_FILE
    latencies: list[float] = []
    with poses_path.open("a", encoding="utf-8") as poses:
        def publish(reports: list[Any], seq: int | None, accepted_s: float | None, revised: bool = False) -> None:
            now = time.time()
            for report in reports:
                line = report.as_dict()
                line["seq"] = seq
                if revised:  # a scan reported before, again: a client that resumes after it still gets this
                    line["revised"] = True
                if accepted_s is not None:
                    line["latency_s"] = round(max(0.0, now - max(accepted_s, ready_s)), 4)
                    latencies.append(line["latency_s"])
                poses.write(json.dumps(line) + "\n")
            poses.flush()
            ctx.progress(len(run.localizer.reports), None, stage=LOCALIZING_SCANS)

        seq, last_seq = 0, None
        idle_since = checked_s = time.monotonic()
        while True:
            chunk_file = ctx.data.chunk_file(session_id, seq)
            if chunk_file.exists():
                accepted_s = os.stat(chunk_file).st_mtime
                publish(run.feed(read_chunk_messages(ctx.data, session_id, seq), seq), seq, accepted_s)
                seq += 1
                idle_since = time.monotonic()
                continue
            if time.monotonic() - checked_s >= STORE_POLL_S:  # the stream's end, a cancel: less often
                checked_s = time.monotonic()
                last_seq = ctx.store.stream_end(session_id)
                if last_seq is not None and seq > last_seq:
                    ended = "finished"
                    break
                ctx.progress(len(run.localizer.reports), None, force=True, stage=LOCALIZING_SCANS)  # cancel: raises
                if time.monotonic() - idle_since >= idle_timeout_s:
                    ended = "idle_timeout"
                    break
            time.sleep(POLL_S)
        remaining, again = run.finish()
        publish(remaining, None, None)
        if again is not None:
            publish([again], None, None, revised=True)
    run.localizer.close()
    ctx.progress(len(run.localizer.reports), None, force=True, stage=LOCALIZING_SCANS)
    if not run.localizer.reports:
        raise JobFailed(f"live stream idle: no scan arrived within idle_timeout_s ({idle_timeout_s:g} s), nothing "
                        "to localise")
    _write_products(ctx, run, poses_path, {"source": "stream", "live": True, "ended": ended, "chunks_used": seq,
                                           "messages": run.messages, "last_seq": last_seq,
                                           "map_job_id": job.config["map_job_id"]}, latencies, bundle, config)


def _write_products(ctx: JobContext, run: LiveLocalizationRun, poses_path: Path, description: dict,
                    latencies: list[float], bundle: Any, config: Any) -> None:
    """A localisation's products from the live reports (each scan's latest: the poses as reported, no
    later scan moved them; a last scan reported again when the stream ended counts as that report), with
    ``poses.jsonl``; the live folder removed."""
    import numpy as np

    from slam_engine.model.result import Trajectory
    from slam_engine.multisession.changes import detect_changes
    from slam_engine.multisession.live_localization import FOUND
    from slam_engine.products.multisession import localization_image, saved_map_grid, write_localization

    localizer = run.localizer
    placed = [r for r in localizer.reports if r.pose is not None]
    summary = {**localizer.summary(), "localised": any(r.state == FOUND for r in localizer.reports),
               "latency_s": _percentiles(latencies)}
    out_dir = ctx.out_dir / "products"
    trajectory = image = None
    confidence = np.zeros(0)
    changes = None
    if placed:
        trajectory = Trajectory(np.array([r.t_s for r in placed]), np.array([r.pose for r in placed]))
        confidence = np.array([r.confidence for r in placed])
        grid = saved_map_grid(bundle, config)
        image = localization_image(grid, trajectory, [localizer.hits[r.scan] for r in placed],
                                   np.array([r.state == FOUND for r in placed]))
        found = [r for r in placed if r.state == FOUND]
        if found and config.changes.enabled:  # what changed, from the scans that matched the map
            changes = (detect_changes(grid, [localizer.hits[r.scan] for r in found], np.array([r.pose for r in found]),
                                      run.projector.origin_v, config.changes), grid)
    files = write_localization(out_dir, summary, trajectory, confidence, image, changes=changes)
    files[POSES_FILE] = Path(shutil.copy2(poses_path, out_dir / POSES_FILE))
    ctx.store.set_input(ctx.job_id, description)
    ctx.store.set_products(ctx.job_id, product_names(files, ctx.out_dir))
    shutil.rmtree(ctx.data.live_dir(ctx.job_id), ignore_errors=True)


def _percentiles(values: list[float]) -> dict | None:
    import numpy as np

    if not values:
        return None
    p50, p95, p99 = np.percentile(values, [50, 95, 99])
    return {"p50": round(float(p50), 4), "p95": round(float(p95), 4), "p99": round(float(p99), 4),
            "max": round(float(max(values)), 4), "count": len(values)}
