"""``python -m bench live``: does a live job keep up with the simulated car streamed at real time?

The simulated car (``simulate(None, seed=0, rig="car", cameras=False)``: an 80 m LiDAR at 10 Hz on the
campus drive, the car of the accuracy table) is written as a log with its ground truth and read back
as stream messages. The API runs in this process on a temporary data folder with one local worker
process; a session gets the car's calibration and a live job with the default mapping settings (30
particles). The messages are then posted in chunks of one second of drive, each when its last second
has passed on the wall clock (``--speed`` faster), with ``--busy`` CPU-bound processes running beside.
Before each post the backlog (scans posted minus the job's ``scans_done``) is sampled; after the last
chunk the stream is finished and the job is followed to its end.

Prints one table (backlog over the drive, the lag after the last chunk, the job's own time spent
mapping and writing live snapshots, the trajectory's ATE against the simulator's ground truth, scored
as the accuracy table scores it) and writes ``live.json`` into the results folder (with a copy as
``bench/results/latest-live.json`` when under ``bench/results``).
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import typer

CHUNK_S = 1.0  # seconds of drive per posted chunk
RESULTS_FILE = "live.json"
LATEST_FILE = "latest-live.json"


@dataclass
class CarStream:
    """The simulated car as a stream: the session's calibration, the chunks' messages, each chunk's end
    (drive time since the first message, s), the ground-truth file the accuracy table scores against
    and the drive time per chunk [s]."""

    calibration: dict[str, Any]
    chunks: list[list[dict[str, Any]]]
    chunk_end_s: list[float]
    ground_truth_path: str
    chunk_s: float

    @property
    def scans(self) -> int:
        return sum(m["type"] == "scan" for chunk in self.chunks for m in chunk)


def car_stream(folder: Path, duration_s: float | None = None, chunk_s: float = CHUNK_S) -> CarStream:
    """The simulated car (seed 0, no cameras; the first ``duration_s`` of the drive, all by default)
    written under ``folder`` as the accuracy table writes it, read back and cut into ``chunk_s`` chunks."""
    from bench.cases import case_for_log
    from service.storage.stream_log import calibration_from_log, messages_of_log
    from slam_engine.formats import load_log
    from slam_engine.simulation import simulate, write_simulated

    drive = simulate(None, seed=0, rig="car", cameras=False, max_duration_s=duration_s)
    out = Path(folder) / f"sim-car-{drive.scenario}"
    out.mkdir(parents=True, exist_ok=True)
    write_simulated(drive, "ece276a-car", out)
    case = case_for_log(out)
    if case.ground_truth_path is None:
        raise RuntimeError(f"the simulated car in {out} has no ground-truth file")
    log = load_log(case.log_path)
    messages = messages_of_log(log)
    t0 = messages[0]["t_s"]
    chunks: list[list[dict[str, Any]]] = []
    for m in messages:
        index = int((m["t_s"] - t0) // chunk_s)
        while len(chunks) <= index:
            chunks.append([])
        chunks[index].append(m)
    kept = [(i, chunk) for i, chunk in enumerate(chunks) if chunk]
    return CarStream(calibration_from_log(log), [chunk for _, chunk in kept],
                     [(i + 1) * chunk_s for i, _ in kept], case.ground_truth_path, chunk_s)


@dataclass
class LiveRecord:
    """What one streamed live job did: the backlog before each post [scans], the job's timings [s]."""

    scans: int
    drive_s: float
    speed: float
    chunk_s: float
    backlog: list[int] = field(default_factory=list)
    wall_s: float | None = None  # first post to the job's end
    lag_s: float | None = None  # last post to every scan mapped
    end_s: float | None = None  # last post to the job's end (back end and products included)
    status: str | None = None
    job: dict[str, Any] = field(default_factory=dict)
    trajectory: list[dict[str, float]] = field(default_factory=list)

    def thirds(self) -> tuple[float, float]:
        """Mean backlog over the first and the last third of the samples [scans]."""
        third = max(1, len(self.backlog) // 3)
        return statistics.fmean(self.backlog[:third]), statistics.fmean(self.backlog[-third:])


def stream_live(client, stream: CarStream, params: dict[str, Any], speed: float = 1.0,
                timeout_s: float = 600.0, say: Callable[[str], None] = lambda line: None) -> LiveRecord:
    """Start a live job on a new session with ``stream``'s calibration, post its chunks at ``speed``
    times real time (chunk k once its drive time has passed on the wall clock), sampling the backlog
    before each post, then finish the stream and follow the job to its end (``timeout_s``)."""
    session = client.post("/v1/sessions", json={"name": "live car", "calibration": stream.calibration})
    if session.status_code != 201:
        raise RuntimeError(f"session refused: {session.text}")
    sid = session.json()["id"]
    created = client.post(f"/v1/sessions/{sid}/jobs", json={**params, "live": True})
    if created.status_code != 202:
        raise RuntimeError(f"live job refused: {created.text}")
    job_id = created.json()["id"]
    deadline = time.monotonic() + timeout_s

    def job() -> dict[str, Any]:
        if time.monotonic() > deadline:
            raise RuntimeError(f"live job {job_id} not done in {timeout_s:.0f} s")
        return client.get(f"/v1/jobs/{job_id}").json()

    while job()["status"] == "queued":
        time.sleep(0.05)
    record = LiveRecord(scans=stream.scans, drive_s=stream.chunk_end_s[-1], speed=speed, chunk_s=stream.chunk_s)
    posted = 0
    started = time.monotonic()
    for seq, (chunk, end_s) in enumerate(zip(stream.chunks, stream.chunk_end_s, strict=True)):
        time.sleep(max(0.0, started + end_s / speed - time.monotonic()))
        if seq > 0:
            record.backlog.append(posted - (job()["scans_done"] or 0))
        response = client.post(f"/v1/sessions/{sid}/chunks", json={"seq": seq, "messages": chunk})
        if response.status_code != 201:
            raise RuntimeError(f"chunk {seq} refused: {response.text}")
        posted += sum(m["type"] == "scan" for m in chunk)
        if seq > 0 and seq % max(1, round(10.0 / stream.chunk_s)) == 0:  # every 10 s of drive
            say(f"  {end_s:5.0f} s of drive posted, backlog {record.backlog[-1]} scans")
    last_post = time.monotonic()
    finished = client.post(f"/v1/sessions/{sid}/chunks/finish", json={})
    if finished.status_code != 200:
        raise RuntimeError(f"finish refused: {finished.text}")
    while (row := job())["status"] in ("queued", "running"):
        if record.lag_s is None and (row["scans_done"] or 0) >= stream.scans:
            record.lag_s = time.monotonic() - last_post
        time.sleep(0.02)
    now = time.monotonic()
    record.lag_s = now - last_post if record.lag_s is None else record.lag_s
    record.wall_s, record.end_s = now - started, now - last_post
    record.status, record.job = row["status"], row
    if row["status"] == "succeeded":
        record.trajectory = client.get(f"/v1/jobs/{job_id}/trajectory").json()["poses"]
    return record


def ate_m(record: LiveRecord, ground_truth_path: str) -> float | None:
    """The live job's ATE against the ground truth [m], scored as the accuracy table scores a run."""
    import numpy as np

    from bench.worker import score
    from slam_engine.evaluation.metrics import read_ground_truth
    from slam_engine.model.result import Trajectory

    if not record.trajectory:
        return None
    poses = record.trajectory
    trajectory = Trajectory(np.array([p["t_s"] for p in poses]),
                            np.array([[p["x_m"], p["y_m"], p["theta_rad"]] for p in poses]))
    return score(trajectory, None, read_ground_truth(ground_truth_path))["ate_m"]


def summary(record: LiveRecord, busy: int, ate: float | None) -> dict[str, Any]:
    """One line of the table (JSON-ready)."""
    first, last = record.thirds() if record.backlog else (None, None)
    live = (record.job.get("input") or {}).get("live_timing") or {}
    return {"busy": busy, "speed": record.speed, "chunk_s": record.chunk_s, "drive_s": record.drive_s,
            "scans": record.scans, "status": record.status, "wall_s": record.wall_s, "lag_s": record.lag_s,
            "end_s": record.end_s,
            "backlog_median": statistics.median(record.backlog) if record.backlog else None,
            "backlog_max": max(record.backlog) if record.backlog else None,
            "backlog_first_third": first, "backlog_last_third": last,
            "snapshots": live.get("snapshots"), "snapshots_s": live.get("snapshots_s"),
            "mapping_s": live.get("mapping_s"),
            "mapping_scans_per_s": record.scans / live["mapping_s"] if live.get("mapping_s") else None,
            "ate_m": ate, "backlog": record.backlog, "error": record.job.get("error")}


def run_live(busy: int, speed: float, duration_s: float | None, params: dict[str, Any], folder: Path,
             chunk_s: float = CHUNK_S, say: Callable[[str], None] = print) -> dict[str, Any]:
    """One streamed live job of the car (API and worker on ``folder``) beside ``busy`` busy processes."""
    from fastapi.testclient import TestClient

    from bench.harness import busy_processes
    from service.api.app import create_app
    from service.settings import Settings

    stream = car_stream(folder / "simulated", duration_s, chunk_s)
    say(f"the simulated car: {stream.chunk_end_s[-1]:.0f} s of drive, {stream.scans} scans, "
        f"{len(stream.chunks)} chunks at {speed:g}x real time, {busy} busy processes beside, "
        f"{os.cpu_count()} CPU cores")
    settings = Settings(data_dir=folder / "data", workers=1)
    with TestClient(create_app(settings)) as client, busy_processes(busy):
        record = stream_live(client, stream, params, speed, say=say)
    return summary(record, busy, ate_m(record, stream.ground_truth_path))


def print_live(results: dict[str, Any], console) -> None:
    """The live table: one line per run."""
    from rich.table import Table

    from bench.report import fmt

    table = Table(title=f"Live car job at real time ({results['params']['particles']} particles; backlog = scans "
                        "posted - scans mapped, sampled before each 1 s chunk)")
    for column in ("busy", "speed", "drive (s)", "scans", "status", "wall (s)", "lag after last chunk (s)",
                   "job end after last chunk (s)", "backlog median / max", "backlog 1st / last third",
                   "snapshots (n / s)", "mapping (s)", "mapping scans/s", "ATE (m)"):
        table.add_column(column)
    for row in results["rows"]:
        table.add_row(str(row["busy"]), f"{row['speed']:g}x", fmt(row["drive_s"], 0), str(row["scans"]),
                      str(row["status"]), fmt(row["wall_s"], 1), fmt(row["lag_s"], 2), fmt(row["end_s"], 1),
                      f"{fmt(row['backlog_median'], 0)} / {fmt(row['backlog_max'], 0)}",
                      f"{fmt(row['backlog_first_third'], 1)} / {fmt(row['backlog_last_third'], 1)}",
                      f"{fmt(row['snapshots'], 0)} / {fmt(row['snapshots_s'], 1)}", fmt(row["mapping_s"], 1),
                      fmt(row["mapping_scans_per_s"], 0), fmt(row["ate_m"], 3))
    console.print(table)


def run_live_table(out: Path, console, busy: int = 1, speed: float = 1.0, duration_s: float | None = None,
                   particles: int = 30, chunk_s: float = CHUNK_S) -> dict[str, Any]:
    """One streamed live job of the car (:func:`run_live`), its table printed and its numbers written to
    ``out / RESULTS_FILE`` (and to ``bench/results/latest-live.json`` when ``out`` is under it)."""
    from bench.harness import code_version, write_results
    from slam_engine.kernels import warm_up

    warm_up()  # as `make bench` and `make serve` do: the job's worker loads the kernels, never compiles them
    out.mkdir(parents=True, exist_ok=True)
    params = {"particles": particles, "seed": 0}
    with tempfile.TemporaryDirectory(prefix="lidarmap-live-") as tmp:
        row = run_live(busy, speed, duration_s, params, Path(tmp), chunk_s,
                       say=lambda line: console.print(line, highlight=False))
    results = {"code": code_version(), "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "cpu_count": os.cpu_count(),
               "params": params, "rows": [row]}
    write_results(results, out, RESULTS_FILE, LATEST_FILE)
    print_live(results, console)
    return results


def live(
    busy: int = typer.Option(1, min=0, max=64, help="CPU-bound processes ('while True: pass') beside the job."),
    speed: float = typer.Option(1.0, min=0.1, max=100.0, help="Stream at this many times real time."),
    duration_s: float | None = typer.Option(None, min=5.0, max=600.0,
                                            help="Stream only the first seconds of the drive (default: all)."),
    particles: int = typer.Option(30, min=1, max=1000, help="Particles of the live job."),
    chunk_s: float = typer.Option(CHUNK_S, min=0.1, max=10.0, help="Seconds of drive per posted chunk."),
    out: Path | None = typer.Option(None, help="Output folder (default bench/results/<date-time>)."),
) -> None:
    """The simulated car streamed through the API at real time into a live job: does it keep up?"""
    from bench.harness import default_out_dir
    from bench.options import report_console

    results = run_live_table(out if out is not None else default_out_dir(), report_console(), busy, speed,
                             duration_s, particles, chunk_s)
    if results["rows"][0]["status"] != "succeeded":
        raise typer.Exit(1)
