"""``python -m bench.live_localization``: a robot localised live in a saved map, through a real service.

Issue #63's live targets (seed 0): the latency from a chunk accepted to its scans' poses readable (p95 <=
100 ms, backlog 0) on a busy 2-core machine, the time from the stream's start to the first confident
pose (<= 5 s of driving) and a drive from another building never reported found.

A ``lidarmap serve`` process (one local worker) on a temporary data folder; the simulated office (seed 0)
uploaded and mapped (10 particles, the robot's 5 Hz LiDAR); then the office driven again (seed 1, with a
10 Hz LiDAR: ``--scan-hz``) streamed into a live job of mode ``localize`` in that map, on a session with the
drive's calibration: its messages cut into chunks of ``chunk_s`` of drive (by the log's stamps), chunk k
posted once its last stamp has passed on the wall clock (real time, ``speed`` times faster), with ``busy``
CPU-bound processes (``while True: pass``) beside. The poses are read as the service makes them
(``LidarmapClient.follow_poses``, server-sent events, in a thread). Before each post the backlog is sampled
(scans posted minus the job's scans reported, and minus the poses the client has read). Then a foreign drive
(the campus robot drive, seed 1, ``foreign_s`` of it, 10 Hz) is streamed the same way into a live job in the
office map. About 3 minutes.

Measured: the service's ``latency_s`` of each pose (chunk file written to pose written) p50/p95/p99/max,
and the latency the client sees (its chunk's post started to the pose read from the event stream; the
chunk a scan was posted in, even when a later chunk's odometry placed it); the backlog (median, max);
the drive time, the travel (ground truth) and the wall time from the stream's start to the first
``found`` pose; the share of scans found after it; the found poses' position error against the
simulator's ground truth (the map's frame carried onto the world by aligning the mapping job's trajectory
with the seed-0 drive's truth: ``align_rigid_2d``); the foreign drive's ``found`` reports (target: none).

Prints a table with the targets beside the measurements and, with an output folder, writes
``live_localization.json`` there (a copy as ``bench/results/latest-live-localization.json`` when under
``bench/results``). ``make bench`` prints it after the live table.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.serve_process import lidarmap_serve

CHUNK_S = 0.5  # seconds of drive per posted chunk
MAP_PARTICLES = 10
FOREIGN_S = 60.0  # seconds of the foreign drive streamed
SCAN_HZ = 10.0  # the streamed drives' LiDAR rate (issue #63's 10 Hz stream; the robot rig's own is 5 Hz)
RESULTS_FILE = "live_localization.json"
LATEST_FILE = "latest-live-localization.json"
TARGETS = {"latency_p95_s": 0.100, "backlog_max": 0, "first_found_drive_s": 5.0, "foreign_found": 0}


@dataclass
class DriveStream:
    """A simulated drive as a stream: its calibration, the chunks' messages, each chunk's end (drive time
    since the first message, s), the drive itself (ground truth: ``drive.pose_at``) and its first stamp."""

    name: str
    drive: Any  # slam_engine.simulation.SimulatedDrive
    calibration: dict[str, Any]
    chunks: list[list[dict[str, Any]]]
    chunk_end_s: list[float]
    t0_s: float
    chunk_s: float

    @property
    def scans(self) -> int:
        return sum(m["type"] == "scan" for chunk in self.chunks for m in chunk)

    def scan_chunks(self) -> list[int]:
        """The index of the chunk each scan (in stream order) is posted in."""
        return [i for i, chunk in enumerate(self.chunks) for m in chunk if m["type"] == "scan"]


def drive_stream(name: str, drive: Any, folder: Path, chunk_s: float = CHUNK_S) -> DriveStream:
    """``drive`` written as a CARMEN log under ``folder / name``, read back as stream messages and cut into
    chunks of ``chunk_s`` of drive by the messages' stamps (empty stretches skipped)."""
    from service.storage.stream_log import calibration_from_log, messages_of_log
    from slam_engine.formats import load_log
    from slam_engine.simulation import write_simulated

    log = load_log(write_simulated(drive, "carmen", folder / name))
    messages = messages_of_log(log)
    t0 = messages[0]["t_s"]
    chunks: list[list[dict[str, Any]]] = []
    for m in messages:
        index = int((m["t_s"] - t0) // chunk_s)
        while len(chunks) <= index:
            chunks.append([])
        chunks[index].append(m)
    kept = [(i, chunk) for i, chunk in enumerate(chunks) if chunk]
    return DriveStream(name, drive, calibration_from_log(log), [c for _, c in kept],
                       [(i + 1) * chunk_s for i, _ in kept], t0, chunk_s)


@dataclass
class LiveRun:
    """What one streamed live localisation did: the reports as the client read them, each with the wall
    clock it was read at, the chunks' post times, the backlog before each post, the job's end."""

    stream: DriveStream
    speed: float
    reports: list[dict[str, Any]] = field(default_factory=list)
    read_at: list[float] = field(default_factory=list)  # time.time() when each report was read
    posted_at: list[float] = field(default_factory=list)  # time.time() when each chunk's post began
    backlog: list[int] = field(default_factory=list)  # scans posted - the job's scans reported
    unread: list[int] = field(default_factory=list)  # scans posted - poses the client has read
    started_s: float = 0.0  # time.time() of the first post
    status: str | None = None
    error: Any = None
    localization: dict[str, Any] = field(default_factory=dict)  # run.json's


def stream_localize(url: str, stream: DriveStream, map_job_id: str, speed: float = 1.0, timeout_s: float = 300.0,
                    say: Callable[[str], None] = lambda line: None) -> LiveRun:
    """A live localize job in ``map_job_id``'s map on a new session with ``stream``'s calibration; its chunks
    posted at ``speed`` times real time while a thread follows the poses; the stream finished and the job
    waited for (``timeout_s``)."""
    import httpx

    from api_schemas.jobs import JobCreate
    from lidarmap.client import LidarmapClient

    run = LiveRun(stream, speed)
    with LidarmapClient(url) as api, LidarmapClient(url) as follower_api:
        sid = api.create_session(f"live {stream.name}", calibration=stream.calibration).id
        job = api.start_job(sid, JobCreate(live=True, mode="localize", map_job_id=map_job_id, idle_timeout_s=60.0))
        deadline = time.monotonic() + timeout_s
        while api.job(job.id).status.value == "queued":
            if time.monotonic() > deadline:
                raise RuntimeError(f"live job {job.id} still queued after {timeout_s:.0f} s")
            time.sleep(0.05)
        failure: list[BaseException] = []

        def follow() -> None:
            try:
                for report in follower_api.follow_poses(job.id):
                    run.read_at.append(time.time())
                    run.reports.append(report)
            except BaseException as error:  # noqa: BLE001 - handed to the main thread
                failure.append(error)

        follower = threading.Thread(target=follow, name=f"poses {stream.name}", daemon=True)
        follower.start()
        posted = 0
        started = time.monotonic()
        run.started_s = time.time()
        for seq, (chunk, end_s) in enumerate(zip(stream.chunks, stream.chunk_end_s, strict=True)):
            time.sleep(max(0.0, started + end_s / speed - time.monotonic()))
            if seq > 0:
                run.backlog.append(posted - (api.job(job.id).scans_done or 0))
                run.unread.append(posted - len(run.reports))
            run.posted_at.append(time.time())
            api.send_chunk(sid, seq, chunk)
            posted += sum(m["type"] == "scan" for m in chunk)
            if seq > 0 and seq % max(1, round(20.0 / stream.chunk_s)) == 0:  # every 20 s of drive
                found = sum(r["state"] == "found" for r in run.reports)
                say(f"  {stream.name}: {end_s:5.1f} s of drive posted, {len(run.reports)} poses read "
                    f"({found} found), backlog {run.backlog[-1]}")
        api.finish_stream(sid)
        done = api.wait(job.id, poll_s=0.1, timeout_s=max(1.0, deadline - time.monotonic()))
        follower.join(timeout=max(1.0, deadline - time.monotonic()))
        if follower.is_alive():
            raise RuntimeError(f"the poses of live job {job.id} still streaming after {timeout_s:.0f} s")
        if failure:
            raise failure[0]
        run.status, run.error = done.status.value, done.error
        if done.status.value == "succeeded":
            record = httpx.get(f"{url}/v1/jobs/{job.id}/run.json", timeout=60.0).json()
            run.localization = record.get("localization") or {}
    return run


def percentiles(values: list[float]) -> dict[str, Any] | None:
    """p50, p95, p99, max and count of ``values`` (None when there are none)."""
    if not values:
        return None
    p50, p95, p99 = np.percentile(values, [50, 95, 99])
    return {"p50": float(p50), "p95": float(p95), "p99": float(p99), "max": float(max(values)), "count": len(values)}


def measure(run: LiveRun, to_world: tuple[np.ndarray, np.ndarray] | None) -> dict[str, Any]:
    """One streamed drive's figures (JSON-ready); ``to_world``: the rotation and translation carrying the
    map's frame onto the simulator's world (found poses scored against the ground truth)."""
    stream, reports = run.stream, run.reports
    scan_chunks = stream.scan_chunks()
    states = [r["state"] for r in reports]
    server = [float(r["latency_s"]) for r in reports if r.get("latency_s") is not None]
    seen: list[float | None] = [
        run.read_at[k] - run.posted_at[scan_chunks[r["scan"]]]
        if 0 <= r["scan"] < len(scan_chunks) and scan_chunks[r["scan"]] < len(run.posted_at) else None
        for k, r in enumerate(reports)]
    client = [value for value in seen if value is not None]
    truth = stream.drive.ground_truth
    steps = np.hypot(*np.diff(truth.poses[:, :2], axis=0).T)
    travel = np.concatenate([[0.0], np.cumsum(steps)])
    first = next((k for k, state in enumerate(states) if state == "found"), None)
    row: dict[str, Any] = {
        "drive": stream.name, "scenario": stream.drive.scenario, "seed": stream.drive.seed,
        "drive_s": stream.chunk_end_s[-1], "scans": stream.scans, "chunks": len(stream.chunks),
        "speed": run.speed, "status": run.status, "error": run.error, "reports": len(reports),
        "in_order": [r["scan"] for r in reports] == list(range(stream.scans)),
        "states": {state: states.count(state) for state in dict.fromkeys(states)},
        "latency_s": percentiles(server), "unplaced_at_end": len(reports) - len(server),
        "client_latency_s": percentiles(client),
        "backlog_median": statistics.median(run.backlog) if run.backlog else None,
        "backlog_max": max(run.backlog) if run.backlog else None,
        "unread_median": statistics.median(run.unread) if run.unread else None,
        "unread_max": max(run.unread) if run.unread else None,
        "found": states.count("found"), "first_found_scan": None, "first_found_drive_s": None,
        "first_found_travel_m": None, "first_found_wall_s": None, "found_share_after_first": None,
        "error_median_m": None, "error_max_m": None, "heading_error_max_rad": None,
        "localization": run.localization, "backlog": run.backlog,
        # every report as read: scan, t_s, state, latency_s (service), read_s (client), error_m (when found)
        "poses": [{"scan": r["scan"], "t_s": r["t_s"], "state": r["state"], "latency_s": r.get("latency_s"),
                   "read_s": None if value is None else round(value, 4), "error_m": None}
                  for r, value in zip(reports, seen, strict=True)],
    }
    if first is None:
        return row
    found_report = reports[first]
    row.update(first_found_scan=found_report["scan"], first_found_drive_s=found_report["t_s"] - stream.t0_s,
               first_found_travel_m=float(np.interp(found_report["t_s"], truth.t_s, travel)),
               first_found_wall_s=run.read_at[first] - run.started_s,
               found_share_after_first=states[first:].count("found") / len(states[first:]))
    if to_world is not None:
        rotation, translation = to_world
        found = [r for r in reports if r["state"] == "found"]
        poses = np.array([r["pose"] for r in found], np.float64)
        true = stream.drive.pose_at(np.array([r["t_s"] for r in found]))
        errors = np.hypot(*(poses[:, :2] @ rotation.T + translation - true[:, :2]).T)
        turn = np.arctan2(rotation[1, 0], rotation[0, 0])
        heading = np.abs(np.angle(np.exp(1j * (poses[:, 2] + turn - true[:, 2]))))
        row.update(error_median_m=float(np.median(errors)), error_max_m=float(errors.max()),
                   heading_error_max_rad=float(heading.max()))
        found_rows = (pose for pose in row["poses"] if pose["state"] == "found")
        for pose, error in zip(found_rows, errors, strict=True):
            pose["error_m"] = round(float(error), 5)
    return row


def run_live_localization(folder: Path, busy: int = 1, speed: float = 1.0, drive_s: float | None = None,
                          map_s: float | None = None, foreign_s: float = FOREIGN_S, chunk_s: float = CHUNK_S,
                          particles: int = MAP_PARTICLES, scan_hz: float | None = SCAN_HZ,
                          say: Callable[[str], None] = print) -> dict[str, Any]:
    """The whole bench on ``folder`` (module docstring): the office (seed 0, its first ``map_s``, all by
    default; the robot rig's 5 Hz LiDAR) mapped through a real service, the office driven again (seed 1, its
    first ``drive_s``) and the campus robot drive (seed 1, ``foreign_s``), both with a ``scan_hz`` LiDAR (None:
    the rig's own), streamed into live localize jobs beside ``busy`` processes. The results (JSON-ready)."""
    from api_schemas.jobs import JobCreate
    from bench.harness import busy_processes, code_version
    from lidarmap.client import LidarmapClient
    from slam_engine.evaluation.metrics import align_rigid_2d
    from slam_engine.kernels import warm_up
    from slam_engine.simulation import simulate, write_simulated

    warm_up()  # as `make bench` and `make serve` do: the job's worker loads the kernels, never compiles them
    mapped = simulate("office", seed=0, cameras=False, max_duration_s=map_s)
    map_log = write_simulated(mapped, "carmen", folder / "office-map")
    again = simulate("office", seed=1, cameras=False, max_duration_s=drive_s, scan_hz=scan_hz)
    office = drive_stream("office", again, folder, chunk_s)
    foreign = drive_stream("campus", simulate("campus", seed=1, rig="robot", cameras=False, max_duration_s=foreign_s,
                                              scan_hz=scan_hz), folder, chunk_s)
    say(f"the office again: {office.chunk_end_s[-1]:.0f} s of drive, {office.scans} scans ({scan_hz or 'rig'} Hz); "
        f"the campus robot: "
        f"{foreign.chunk_end_s[-1]:.0f} s, {foreign.scans} scans; {chunk_s:g} s chunks at {speed:g}x real time, "
        f"{busy} busy processes beside, {os.cpu_count()} CPU cores")
    with lidarmap_serve(folder / "data", workers=1) as (url, _):
        with LidarmapClient(url) as api:
            session = api.create_session("office map")
            api.upload_log(session.id, map_log)
            begun = time.monotonic()
            job = api.wait(api.start_job(session.id, JobCreate(particles=particles, seed=0)).id, poll_s=0.2,
                           timeout_s=600.0)
            mapping_s = time.monotonic() - begun
            if job.status.value != "succeeded":
                raise RuntimeError(f"mapping the office failed: {job.error}")
            trajectory = api.trajectory(job.id).poses
        t = np.array([p.t_s for p in trajectory])
        to_world = align_rigid_2d(np.array([[p.x_m, p.y_m] for p in trajectory]), mapped.pose_at(t)[:, :2])
        say(f"the office mapped ({particles} particles) in {mapping_s:.1f} s")
        with busy_processes(busy):
            office_run = stream_localize(url, office, job.id, speed, say=say)
            foreign_run = stream_localize(url, foreign, job.id, speed, say=say)
    return {"code": code_version(), "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "cpu_count": os.cpu_count(),
            "busy": busy, "speed": speed, "chunk_s": chunk_s, "scan_hz": scan_hz, "targets": TARGETS,
            "map": {"scenario": "office", "seed": 0, "particles": particles, "scans": len(mapped.ground_truth.t_s),
                    "mapping_s": mapping_s},
            "office": measure(office_run, to_world), "foreign": measure(foreign_run, to_world)}


def _ms(value: float | None) -> str:
    return "–" if value is None else f"{1000 * value:.0f} ms"


def _met(ok: bool | None) -> str:
    return "–" if ok is None else ("met" if ok else "**not met**")


def table(results: dict[str, Any]) -> str:
    """The measurements beside issue #63's targets (markdown)."""
    office, foreign = results["office"], results["foreign"]
    lat, seen = office["latency_s"] or {}, office["client_latency_s"] or {}
    p95 = lat.get("p95")
    rate = f"{results['scan_hz']:g} Hz" if results.get("scan_hz") else "the rig's 5 Hz"
    lines = [f"Live localisation: the simulated office (seed 0) mapped ({results['map']['particles']} particles), "
             f"driven again (seed 1, {office['drive_s']:.0f} s, {office['scans']} scans at {rate}) and streamed at "
             f"{results['speed']:g}x real time in {results['chunk_s']:g} s chunks beside {results['busy']} busy "
             f"processes, {results['cpu_count']} CPU cores",
             "", "| measure | target | measured | |", "|---|---|---|---|"]
    lines.append(f"| latency, chunk accepted to pose written (service `latency_s`): p95 | <= "
                 f"{_ms(TARGETS['latency_p95_s'])} | {_ms(p95)} (p50 {_ms(lat.get('p50'))}, p99 "
                 f"{_ms(lat.get('p99'))}, max {_ms(lat.get('max'))}; {lat.get('count', 0)} scans) | "
                 f"{_met(None if p95 is None else p95 <= TARGETS['latency_p95_s'])} |")
    lines.append(f"| latency the client sees, its chunk posted to pose read (events): p95 | – | {_ms(seen.get('p95'))} "
                 f"(p50 {_ms(seen.get('p50'))}, p99 {_ms(seen.get('p99'))}, max {_ms(seen.get('max'))}) | |")
    backlog = office["backlog_max"]
    lines.append(f"| backlog before each chunk (scans posted - reported): median / max | "
                 f"{TARGETS['backlog_max']} | {office['backlog_median']} / {backlog} (unread by the client: "
                 f"{office['unread_median']} / {office['unread_max']}) | "
                 f"{_met(None if backlog is None else backlog <= TARGETS['backlog_max'])} |")
    first = office["first_found_drive_s"]
    measured = "never found" if first is None else (
        f"{first:.1f} s of driving, {office['first_found_travel_m']:.1f} m (scan {office['first_found_scan']}; "
        f"wall {office['first_found_wall_s']:.1f} s)")
    lines.append(f"| stream start to first confident (found) pose | <= {TARGETS['first_found_drive_s']:g} s of "
                 f"driving | {measured} | {_met(first is not None and first <= TARGETS['first_found_drive_s'])} |")
    share = office["found_share_after_first"]
    lines.append(f"| scans found after the first found | – | {'–' if share is None else f'{100 * share:.1f} %'} "
                 f"({office['found']} of {office['scans']} scans; states {office['states']}) | |")
    error = "–" if office["error_median_m"] is None else (
        f"{office['error_median_m']:.3f} / {office['error_max_m']:.3f} m (heading max "
        f"{office['heading_error_max_rad']:.3f} rad)")
    lines.append(f"| found poses against the ground truth: median / max | – | {error} | |")
    lines.append(f"| foreign drive (campus robot, seed 1, {foreign['drive_s']:.0f} s, {foreign['scans']} scans), "
                 f"live: scans reported found | never | {foreign['found']} (states {foreign['states']}) | "
                 f"{_met(foreign['found'] == TARGETS['foreign_found'])} |")
    in_order = office["in_order"] and foreign["in_order"]
    lines.append(f"\nthe office mapped in {results['map']['mapping_s']:.1f} s; jobs {office['status']} / "
                 f"{foreign['status']}; every scan reported once in order: {in_order}")
    return "\n".join(lines)


def run_live_localization_table(out: Path | None, console, busy: int = 1, speed: float = 1.0,
                                drive_s: float | None = None, map_s: float | None = None,
                                foreign_s: float = FOREIGN_S, chunk_s: float = CHUNK_S,
                                scan_hz: float | None = SCAN_HZ) -> dict[str, Any]:
    """The bench (:func:`run_live_localization`), its table printed and, with ``out``, its numbers written
    to ``out / RESULTS_FILE`` (and to ``bench/results/latest-live-localization.json`` when under it)."""
    from bench.harness import write_results

    console.print("\n[bold]Live localisation[/bold]: the office streamed at real time into a live localize job "
                  "(python -m bench.live_localization)")
    with tempfile.TemporaryDirectory(prefix="lidarmap-live-localization-") as tmp:
        results = run_live_localization(Path(tmp), busy, speed, drive_s, map_s, foreign_s, chunk_s, scan_hz=scan_hz,
                                        say=lambda line: console.print(line, highlight=False))
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        write_results(results, out, RESULTS_FILE, LATEST_FILE)
    console.print(table(results), highlight=False)
    return results


def main(argv: list[str] | None = None) -> int:
    from bench.options import report_console

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--busy", type=int, default=1, help="CPU-bound processes beside the streams (default 1)")
    parser.add_argument("--speed", type=float, default=1.0, help="stream at this many times real time")
    parser.add_argument("--drive-s", type=float, default=None, help="stream only the office drive's first seconds")
    parser.add_argument("--foreign-s", type=float, default=FOREIGN_S, help="seconds of the foreign drive")
    parser.add_argument("--chunk-s", type=float, default=CHUNK_S, help="seconds of drive per chunk")
    parser.add_argument("--scan-hz", type=float, default=SCAN_HZ,
                        help="the streamed drives' LiDAR rate (default 10; 0: the robot rig's own, 5 Hz)")
    parser.add_argument("--out", type=Path, default=None, help="write live_localization.json into this folder")
    args = parser.parse_args(argv)
    if args.busy < 0 or args.speed <= 0 or args.chunk_s <= 0 or args.foreign_s <= 2 or args.scan_hz < 0:
        parser.error("--busy >= 0, --speed > 0, --chunk-s > 0, --foreign-s > 2 and --scan-hz >= 0 are needed")
    results = run_live_localization_table(args.out, report_console(), args.busy, args.speed, args.drive_s,
                                          foreign_s=args.foreign_s, chunk_s=args.chunk_s, scan_hz=args.scan_hz or None)
    return 0 if results["office"]["status"] == "succeeded" and results["foreign"]["status"] == "succeeded" else 1


if __name__ == "__main__":
    raise SystemExit(main())
