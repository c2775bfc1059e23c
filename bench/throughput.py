"""``python -m bench throughput`` (or ``python -m bench.throughput``): mapping jobs per minute
through the Celery runner with 1 and with 2 workers.

Starts a private redis-server on a free loopback port, ``lidarmap worker`` processes and the API
(in this process), uploads one simulated office drive, warms every worker up with one job (imports
and numba's cache load are not throughput), then submits ``--jobs`` jobs at once and times them
from the first POST to the last job's end. Needs redis-server on PATH (Debian: redis-server).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import typer

REPO_ROOT = Path(__file__).resolve().parent.parent


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def redis_server(folder: Path) -> Iterator[str]:
    """A throw-away redis-server on a free loopback port (no persistence, files in ``folder``);
    yields its URL once it answers PING (the benchmark and the Celery runner tests use it)."""
    server = shutil.which("redis-server")
    if server is None:
        raise typer.BadParameter("redis-server not found on PATH (Debian: apt-get install redis-server)")
    port = free_port()
    process = subprocess.Popen([server, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly",
                                "no", "--dir", str(folder)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 10
        while True:
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=0.2) as connection:
                    connection.sendall(b"PING\r\n")
                    if connection.recv(16).startswith(b"+PONG"):
                        break
            except OSError:
                pass
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("redis-server did not start")
            time.sleep(0.05)
        yield f"redis://127.0.0.1:{port}/0"
    finally:
        process.terminate()
        process.wait(timeout=10)


@contextmanager
def workers(count: int, env: dict[str, str], folder: Path) -> Iterator[list[subprocess.Popen]]:
    """``count`` ``lidarmap worker`` processes (concurrency 1 each), each in its own process group."""
    processes = []
    try:
        for i in range(count):
            with (folder / f"worker{i}.log").open("wb") as log:
                processes.append(subprocess.Popen(
                    [sys.executable, "-m", "lidarmap.cli", "worker", "--concurrency", "1",
                     "--hostname", f"bench{i}@%h", "--loglevel", "warning"],
                    cwd=REPO_ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True))
        yield processes
    finally:
        for process in processes:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGTERM)
        for process in processes:
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()


def measure(n_workers: int, n_jobs: int, log_path: Path, job: dict, folder: Path) -> dict:
    """One round: ``n_workers`` workers, ``n_jobs`` jobs; returns the timings."""
    from fastapi.testclient import TestClient

    from service.api.app import create_app
    from service.settings import Settings

    folder.mkdir(parents=True)
    with redis_server(folder) as url:
        env = {**os.environ, "PYTHONPATH": str(REPO_ROOT), "LIDARMAP_BROKER_URL": url,
               "LIDARMAP_DATA_DIR": str(folder / "data")}
        settings = Settings(data_dir=folder / "data", runner="celery", broker_url=url)
        with workers(n_workers, env, folder), TestClient(create_app(settings)) as client:
            deadline = time.monotonic() + 120
            while client.get("/readyz").json()["workers"]["workers_alive"] < n_workers:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"workers did not start: see {folder}/worker*.log")
                time.sleep(0.25)
            session = client.post("/v1/sessions", json={"name": "throughput"}).json()["id"]
            with log_path.open("rb") as f:
                response = client.post(f"/v1/sessions/{session}/logs", files={"file": (log_path.name, f)})
            if response.status_code != 201:
                raise RuntimeError(f"upload failed: {response.text}")

            def run(count: int) -> tuple[float, list[dict]]:
                t0 = time.monotonic()
                ids = [client.post(f"/v1/sessions/{session}/jobs", json=job).json()["id"] for _ in range(count)]
                done: dict[str, dict] = {}
                while len(done) < count:
                    for job_id in ids:
                        if job_id not in done:
                            row = client.get(f"/v1/jobs/{job_id}").json()
                            if row["status"] in ("succeeded", "failed", "cancelled"):
                                done[job_id] = row
                    time.sleep(0.1)
                return time.monotonic() - t0, list(done.values())

            run(n_workers)  # warm-up: one job per worker
            elapsed_s, rows = run(n_jobs)
    failed = [r for r in rows if r["status"] != "succeeded"]
    if failed:
        raise RuntimeError(f"{len(failed)} job(s) did not succeed, e.g. {failed[0]['error']}")
    return {"workers": n_workers, "jobs": n_jobs, "elapsed_s": elapsed_s, "jobs_per_min": 60.0 * n_jobs / elapsed_s}


def throughput(
    jobs: int = typer.Option(20, min=1, max=1000, help="Jobs per round."),
    worker_counts: str = typer.Option("1,2", "--workers", help="Worker counts to compare, e.g. '1,2,4'."),
    particles: int = typer.Option(10, min=1, max=1000, help="Particles per job."),
    duration_s: float = typer.Option(40.0, min=5.0, max=600.0, help="Length of the simulated drive, seconds."),
    out: Path | None = typer.Option(None, help="Also write the numbers to this JSON file."),
) -> None:
    """Jobs per minute through the Celery runner (real Redis, real workers) with 1 and 2 workers."""
    from slam_engine.simulation import simulate, write_simulated

    try:
        counts = [int(c) for c in worker_counts.split(",") if c.strip()]
    except ValueError:
        raise typer.BadParameter(f"{worker_counts!r} is not a list like '1,2'", param_hint="--workers") from None
    if not counts or min(counts) < 1:
        raise typer.BadParameter("worker counts must be positive", param_hint="--workers")
    job = {"particles": particles, "seed": 1, "resolution_m": 0.1, "snapshot_every_scans": 0}
    with tempfile.TemporaryDirectory(prefix="lidarmap-throughput-") as tmp:
        folder = Path(tmp)
        drive = simulate("office", seed=3, rig="carmen-robot", max_duration_s=duration_s)
        log_path = write_simulated(drive, "carmen", folder / "sim")
        scans = len(drive.ground_truth.t_s)
        print(f"{jobs} jobs of a simulated office drive ({duration_s:.0f} s, {scans} scans), {particles} particles, "
              f"on {os.cpu_count()} CPU cores", flush=True)
        results = []
        for count in counts:
            result = measure(count, jobs, log_path, job, folder / f"round-{count}")
            results.append(result)
            print(f"  {count} worker(s): {result['elapsed_s']:6.1f} s  {result['jobs_per_min']:6.1f} jobs/min  "
                  f"x{result['jobs_per_min'] / results[0]['jobs_per_min']:.2f}", flush=True)
    if out is not None:
        out.write_text(json.dumps({"particles": particles, "duration_s": duration_s, "scans": scans,
                                   "cpu_count": os.cpu_count(), "rounds": results}, indent=2))


if __name__ == "__main__":
    app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)
    app.command()(throughput)
    app(prog_name="python -m bench.throughput")
