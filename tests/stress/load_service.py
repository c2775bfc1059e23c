"""Load the real service over loopback HTTP and report figures.

    python -m tests.stress.load_service            # 50 uploads + jobs, 10 000 streamed chunks
    python -m tests.stress.load_service --uploads 10 --chunks 2000   # a quicker run

The service runs with uvicorn in a subprocess on a random 127.0.0.1 port with a temporary data
folder. Part 1: ``--uploads`` concurrent uploads of real logs from the shared datasets (httpx,
asyncio), one mapping job each (1 particle, 0.5 m cells: minutes on 2 cores), while a poller
reads GET /v1/jobs/{id} at 20 requests/s; every upload's sha256 must match, every job must end
succeeded, no request may fail. Part 2: a simulated log streamed as ``--chunks`` chunks of 1-2
messages from 4 concurrent senders, with duplicates and retried chunks, must map exactly like
the same log uploaded whole (same trajectory, same occupancy PNG).
"""

from __future__ import annotations

import argparse
import asyncio
import hashlib
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
JOB_PARAMS = {"particles": 1, "resolution_m": 0.5, "linear_update_m": 2.0, "angular_update_rad": 1.0,
              "snapshot_every_scans": 0}
LOGS = ("benchmark/intel.clf", "breezyslam/exp1.dat", "breezyslam/exp2.dat")
POLL_HZ = 20.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServiceProcess:
    """``lidarmap`` under uvicorn in its own process group on a random loopback port."""

    def __init__(self, data_dir: Path, env: dict[str, str] | None = None, job_function: str | None = None,
                 start_timeout_s: float = 120.0):
        self.data_dir = Path(data_dir)
        self.port = free_port()
        self.base_url = f"http://127.0.0.1:{self.port}"
        self.env = {**os.environ, "LIDARMAP_DATA_DIR": str(self.data_dir), "LIDARMAP_MIN_FREE_BYTES": "0",
                    "PYTHONPATH": os.pathsep.join([str(HERE), str(REPO), os.environ.get("PYTHONPATH", "")]),
                    **(env or {})}
        if job_function:
            self.env["LIDARMAP_TEST_JOB_FUNCTION"] = job_function
        self.start_timeout_s = start_timeout_s
        self.process: subprocess.Popen | None = None
        self.client = httpx.Client(base_url=self.base_url, timeout=60.0)

    def __enter__(self) -> ServiceProcess:
        self.process = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "stress_app:create", "--factory", "--host", "127.0.0.1",
             "--port", str(self.port), "--log-level", "warning"],
            env=self.env, cwd=str(REPO), start_new_session=True)
        deadline = time.monotonic() + self.start_timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"the service exited with {self.process.returncode} while starting")
            try:
                if self.client.get("/readyz").status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"the service did not become ready in {self.start_timeout_s} s")

    def __exit__(self, *exc) -> None:
        self.stop()

    def stop(self) -> None:
        """SIGTERM (a clean shutdown), SIGKILL to the group after 30 s."""
        self.client.close()
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait(timeout=10)

    def kill_hard(self) -> None:
        """SIGKILL to the server and every process it started (workers, loader): a crash."""
        assert self.process is not None
        os.killpg(self.process.pid, signal.SIGKILL)
        self.process.wait(timeout=10)

    def get(self, path: str, **kwargs) -> Any:
        response = self.client.get(path, **kwargs)
        response.raise_for_status()
        return response.json()

    def post(self, path: str, **kwargs) -> Any:
        response = self.client.post(path, **kwargs)
        if response.status_code >= 300:
            raise RuntimeError(f"POST {path}: {response.status_code} {response.text}")
        return response.json()

    def wait_job(self, job_id: str, statuses: set[str] | None = None, timeout_s: float = 600.0) -> dict:
        statuses = statuses or {"succeeded", "failed", "cancelled"}
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            job = self.get(f"/v1/jobs/{job_id}")
            if job["status"] in statuses:
                return job
            time.sleep(0.1)
        raise RuntimeError(f"job {job_id} did not reach {statuses} in {timeout_s} s")


# ---- part 1: concurrent uploads and jobs, polled ------------------------------------------------


@dataclass
class LoadReport:
    uploads: int = 0
    upload_bytes: int = 0
    sha256_mismatches: int = 0
    jobs_succeeded: int = 0
    jobs_failed: list[str] = field(default_factory=list)
    failed_requests: list[str] = field(default_factory=list)
    upload_latency_s: list[float] = field(default_factory=list)
    poll_latency_s: list[float] = field(default_factory=list)
    wall_s: float = 0.0

    @property
    def ok(self) -> bool:
        return not (self.sha256_mismatches or self.jobs_failed or self.failed_requests) and self.uploads > 0


def percentile_ms(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values) * 1000.0, q)) if values else float("nan")


async def _upload_and_start(client: httpx.AsyncClient, path: Path, content: bytes, index: int,
                            report: LoadReport) -> str | None:
    session = (await client.post("/v1/sessions", json={"name": f"load {index}"})).json()["id"]
    t0 = time.monotonic()
    response = await client.post(f"/v1/sessions/{session}/logs", files={"file": (path.name, content)})
    report.upload_latency_s.append(time.monotonic() - t0)
    if response.status_code != 201:
        report.failed_requests.append(f"upload {index} ({path.name}): {response.status_code} {response.text[:200]}")
        return None
    report.uploads += 1
    report.upload_bytes += len(content)
    if response.json()["sha256"] != hashlib.sha256(content).hexdigest():
        report.sha256_mismatches += 1
    job = await client.post(f"/v1/sessions/{session}/jobs", json=JOB_PARAMS)
    if job.status_code != 202:
        report.failed_requests.append(f"job {index}: {job.status_code} {job.text[:200]}")
        return None
    return job.json()["id"]


async def _poll(client: httpx.AsyncClient, job_ids: list[str], done: asyncio.Event, report: LoadReport) -> None:
    """GET /v1/jobs/{id} round-robin at POLL_HZ until ``done``."""
    period, k = 1.0 / POLL_HZ, 0
    next_at = time.monotonic()
    while not done.is_set():
        if job_ids:
            job_id = job_ids[k % len(job_ids)]
            k += 1
            t0 = time.monotonic()
            try:
                response = await client.get(f"/v1/jobs/{job_id}")
                if response.status_code != 200:
                    report.failed_requests.append(f"GET job: {response.status_code} {response.text[:200]}")
            except httpx.HTTPError as exc:
                report.failed_requests.append(f"GET job: {type(exc).__name__}: {exc}")
            report.poll_latency_s.append(time.monotonic() - t0)
        next_at += period
        await asyncio.sleep(max(0.0, next_at - time.monotonic()))


async def run_load(base_url: str, logs: list[Path], uploads: int, timeout_s: float = 1800.0) -> LoadReport:
    report = LoadReport()
    contents = {path: path.read_bytes() for path in logs}
    t0 = time.monotonic()
    limits = httpx.Limits(max_connections=uploads + 8)
    async with httpx.AsyncClient(base_url=base_url, timeout=600.0, limits=limits) as client:
        job_ids: list[str] = []
        done = asyncio.Event()
        poller = asyncio.create_task(_poll(client, job_ids, done, report))

        async def one(i: int) -> None:
            path = logs[i % len(logs)]
            job_id = await _upload_and_start(client, path, contents[path], i, report)
            if job_id:
                job_ids.append(job_id)

        await asyncio.gather(*(one(i) for i in range(uploads)))
        deadline = time.monotonic() + timeout_s
        pending = set(job_ids)
        while pending and time.monotonic() < deadline:
            await asyncio.sleep(1.0)
            listed = (await client.get("/v1/jobs", params={"limit": 1000})).json()["data"]
            for job in listed:
                if job["id"] in pending and job["status"] not in ("queued", "running"):
                    pending.discard(job["id"])
                    if job["status"] == "succeeded":
                        report.jobs_succeeded += 1
                    else:
                        report.jobs_failed.append(f"{job['id']}: {job['status']} {job['error']}")
        report.jobs_failed += [f"{j}: not finished in {timeout_s} s" for j in pending]
        done.set()
        await poller
    report.wall_s = time.monotonic() - t0
    return report


# ---- part 2: a long stream with duplicates and retries --------------------------------------------


@dataclass
class StreamReport:
    chunks: int = 0
    posts: int = 0
    duplicates_answered: int = 0
    failed_requests: list[str] = field(default_factory=list)
    chunk_latency_s: list[float] = field(default_factory=list)
    same_trajectory: bool = False
    same_map: bool = False
    scans: int = 0
    wall_s: float = 0.0

    @property
    def ok(self) -> bool:
        return self.same_trajectory and self.same_map and not self.failed_requests


def stream_log(chunks: int, out_dir: Path) -> Path:
    """A simulated CARMEN log long enough for ``chunks`` chunks of 1-2 messages."""
    from slam_engine.simulation import simulate, write_simulated

    # the office loop lasts 100 s with odometry at 20 Hz: the LiDAR rate makes up the messages needed
    scan_hz = float(np.clip((chunks * 1.5 - 2000) / 100.0, 5.0, 400.0))
    drive = simulate("office", seed=5, rig="carmen-robot", scan_hz=scan_hz)
    return write_simulated(drive, "carmen", out_dir)


async def run_stream(base_url: str, log_path: Path, chunks: int, seed: int = 0) -> StreamReport:
    from service.storage.stream_log import calibration_from_log, messages_of_log
    from slam_engine.formats import load_log

    report = StreamReport()
    rng = random.Random(seed)
    loaded = load_log(log_path)
    messages = messages_of_log(loaded)  # exactly what the upload route will map
    sizes, start = [], 0
    while start < len(messages):
        sizes.append(min(rng.choice((1, 2)), len(messages) - start))
        start += sizes[-1]
    bounds = np.concatenate([[0], np.cumsum(sizes)])
    pieces = [messages[bounds[i]:bounds[i + 1]] for i in range(len(sizes))]
    report.chunks = len(pieces)
    t0 = time.monotonic()
    async with httpx.AsyncClient(base_url=base_url, timeout=120.0) as client:
        whole = (await client.post("/v1/sessions", json={"name": "whole"})).json()["id"]
        response = await client.post(f"/v1/sessions/{whole}/logs",
                                     files={"file": (log_path.name, log_path.read_bytes())})
        assert response.status_code == 201, response.text
        streamed = (await client.post("/v1/sessions", json={"name": "streamed",
                                                             "calibration": calibration_from_log(loaded)})).json()["id"]
        url = f"/v1/sessions/{streamed}/chunks"
        # send order: shuffled within windows of 8 (reordering), some chunks twice (duplicates),
        # some sent, "lost", and sent again (retries)
        order = list(range(len(pieces)))
        for w in range(0, len(order), 8):
            window = order[w:w + 8]
            rng.shuffle(window)
            order[w:w + 8] = window
        sends = []
        for seq in order:
            sends.append(seq)
            if rng.random() < 0.05:
                sends.append(seq)  # a duplicate
        queue: asyncio.Queue[int] = asyncio.Queue()
        for seq in sends:
            queue.put_nowait(seq)

        async def sender() -> None:
            while not queue.empty():
                seq = queue.get_nowait()
                body = {"seq": seq, "messages": pieces[seq]}
                for attempt in range(2 if rng.random() < 0.02 else 1):  # a retry after a "lost" answer
                    t = time.monotonic()
                    r = await client.post(url, json=body)
                    report.chunk_latency_s.append(time.monotonic() - t)
                    report.posts += 1
                    if r.status_code == 200 and r.json()["duplicate"]:
                        report.duplicates_answered += 1
                    elif r.status_code != 201:
                        report.failed_requests.append(f"chunk {seq} try {attempt}: {r.status_code} {r.text[:200]}")

        await asyncio.gather(*(sender() for _ in range(4)))
        state = (await client.get(url)).json()
        if state["contiguous_through"] != len(pieces) - 1:
            report.failed_requests.append(f"stream incomplete: {state}")
        ids = []
        for sid in (whole, streamed):
            r = await client.post(f"/v1/sessions/{sid}/jobs", json={**JOB_PARAMS, "particles": 3, "seed": 7})
            ids.append(r.json()["id"])
        jobs = []
        for job_id in ids:
            while (job := (await client.get(f"/v1/jobs/{job_id}")).json())["status"] in ("queued", "running"):
                await asyncio.sleep(0.5)
            if job["status"] != "succeeded":
                report.failed_requests.append(f"job {job_id}: {job['status']} {job['error']}")
            jobs.append(job)
        if all(j["status"] == "succeeded" for j in jobs):
            a, b = [(await client.get(f"/v1/jobs/{j}/trajectory")).json()["poses"] for j in ids]
            report.same_trajectory, report.scans = a == b, len(a)
            pa, pb = [(await client.get(f"/v1/jobs/{j}/occupancy.png")).content for j in ids]
            report.same_map = pa == pb
    report.wall_s = time.monotonic() - t0
    return report


# ---- command --------------------------------------------------------------------------------------


def table(rows: list[tuple[str, Any]]) -> str:
    width = max(len(name) for name, _ in rows)
    return "\n".join(f"{name:<{width}}  {value}" for name, value in rows)


def datasets_root() -> Path:
    return Path(os.environ.get("LIDARMAP_DATASETS") or REPO.parent / "shared" / "datasets")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--uploads", type=int, default=50)
    parser.add_argument("--chunks", type=int, default=10_000)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args(argv)
    logs = [datasets_root() / name for name in LOGS]
    missing = [str(p) for p in logs if not p.exists()]
    if missing:
        print(f"datasets missing: {missing} (set LIDARMAP_DATASETS)", file=sys.stderr)
        return 2
    ok = True
    with tempfile.TemporaryDirectory(prefix="lidarmap-load-") as tmp:
        env = {"LIDARMAP_WORKERS": str(args.workers)}
        with ServiceProcess(Path(tmp) / "data", env=env) as server:
            if args.uploads:
                load = asyncio.run(run_load(server.base_url, logs, args.uploads))
                ok &= load.ok
                print(table([
                    ("concurrent uploads (real logs)", f"{load.uploads} of {args.uploads}, "
                                                       f"{load.upload_bytes / 1e6:.1f} MB"),
                    ("sha256 mismatches", load.sha256_mismatches),
                    ("jobs succeeded", f"{load.jobs_succeeded} of {args.uploads}"),
                    ("failed requests", len(load.failed_requests)),
                    ("upload latency p50 / p99 [ms]", f"{percentile_ms(load.upload_latency_s, 50):.0f} / "
                                                      f"{percentile_ms(load.upload_latency_s, 99):.0f}"),
                    (f"GET /v1/jobs/{{id}} at {POLL_HZ:.0f}/s: requests", len(load.poll_latency_s)),
                    ("GET /v1/jobs/{id} latency p50 / p99 [ms]", f"{percentile_ms(load.poll_latency_s, 50):.1f} / "
                                                                 f"{percentile_ms(load.poll_latency_s, 99):.1f}"),
                    ("wall time [s]", f"{load.wall_s:.0f}"),
                ]))
                for line in load.failed_requests[:10] + load.jobs_failed[:10]:
                    print("FAIL", line)
            if args.chunks:
                print()
                log_path = stream_log(args.chunks, Path(tmp) / "stream-log")
                stream = asyncio.run(run_stream(server.base_url, log_path, args.chunks))
                ok &= stream.ok
                print(table([
                    ("streamed chunks (1-2 messages)", stream.chunks),
                    ("POSTs incl. duplicates and retries", stream.posts),
                    ("answered as duplicates (200)", stream.duplicates_answered),
                    ("failed requests", len(stream.failed_requests)),
                    ("chunk POST latency p50 / p99 [ms]", f"{percentile_ms(stream.chunk_latency_s, 50):.1f} / "
                                                          f"{percentile_ms(stream.chunk_latency_s, 99):.1f}"),
                    ("scans mapped", stream.scans),
                    ("same trajectory as the upload", stream.same_trajectory),
                    ("same occupancy PNG as the upload", stream.same_map),
                    ("wall time [s]", f"{stream.wall_s:.0f}"),
                ]))
                for line in stream.failed_requests[:10]:
                    print("FAIL", line)
    print("\nRESULT:", "ok" if ok else "FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
