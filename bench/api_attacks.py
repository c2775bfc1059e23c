"""``python -m bench.api_attacks``: the API process under the adversarial requests of issue 41, against
a real ``lidarmap serve``: cold tiles of a huge grid, concurrent HEAD and GET of a long trajectory, a
huge request header. Prints, per attack, the API process's peak resident memory and the slowest
``/healthz`` answer while it ran (targets: <= 600 MB, <= 1 s).

The huge grid is the probe's own: a log of three scans 400 m apart mapped with ``{"particles": 1}``; the
long trajectory is a finished job of 400 000 poses written into the data folder before the service
starts (mapping 400 000 scans would take an hour)."""

from __future__ import annotations

import math
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import psutil

MB = 1024**2
ROOT = Path(__file__).resolve().parents[1]


# ---- a job written straight into the data folder ----------------------------------------------------


def stored_job(data_dir: Path, write: Callable[[Path], dict[str, str]]) -> str:
    """A finished job in the data folder's store, its products written by ``write(job_dir)`` (which
    returns product name -> path relative to the job folder); returns the job id."""
    from api_schemas.jobs import JobSource, JobStatus
    from service.storage.data_dir import DataDir
    from service.storage.store import open_store

    data = DataDir(data_dir)
    data.create()
    store = open_store("", data.database)
    store.initialise()
    try:
        session = store.create_session("", "attack", None, None, None)
        job = store.create_job(session.id, "", JobSource.LOG, None, {"mode": "map"})
        products = write(data.job_dir(job.id))
        store.set_products(job.id, products)
        store.mark_running(job.id, os.getpid())
        store.finish(job.id, JobStatus.SUCCEEDED)
    finally:
        store.close()
    return job.id


def long_trajectory_job(data_dir: Path, poses: int) -> str:
    """A finished job whose SLAM trajectory and dead reckoning have ``poses`` poses (a 1 km spiral)."""
    from slam_engine.model.result import Trajectory
    from slam_engine.products import write_trajectory_json, write_trajectory_tum

    def write(job_dir: Path) -> dict[str, str]:
        t = np.arange(poses) * 0.05
        angle = np.linspace(0.0, 40 * math.pi, poses)
        xy = np.column_stack([angle * np.cos(angle), angle * np.sin(angle)]) * 4.0
        traj = Trajectory(t_s=t, poses=np.column_stack([xy, angle]))
        products = job_dir / "products"
        products.mkdir(parents=True, exist_ok=True)
        for stem in ("trajectory", "dead_reckoning"):
            write_trajectory_json(traj, products / f"{stem}.json")
            write_trajectory_tum(traj, products / f"{stem}.tum")
        return {f"{stem}.{ext}": f"products/{stem}.{ext}" for stem in ("trajectory", "dead_reckoning")
                for ext in ("json", "tum")}

    return stored_job(data_dir, write)


def grid_job(data_dir: Path, cells: int, legacy: bool = False) -> str:
    """A finished job whose occupancy grid is ``cells`` x ``cells`` float32 (a square room's walls and a
    diagonal), written as the worker writes it, or (``legacy``) as a plain .npz of the grid, the way
    versions before tile pyramids did."""
    from service.jobs.products import GRID_FILE, save_grid
    from slam_engine.model.result import OccupancyGrid

    def write(job_dir: Path) -> dict[str, str]:
        log_odds = np.zeros((cells, cells), np.float32)
        log_odds[[0, -1], :] = 4.0
        log_odds[:, [0, -1]] = 4.0
        idx = np.arange(cells)
        log_odds[idx, idx] = 3.0
        log_odds[cells // 4: 3 * cells // 4, cells // 4: 3 * cells // 4] = -2.0
        job_dir.mkdir(parents=True, exist_ok=True)
        if legacy:
            np.savez(job_dir / GRID_FILE, log_odds=log_odds, resolution_m=0.05, origin_x_m=0.0, origin_y_m=0.0)
        else:
            save_grid(OccupancyGrid(log_odds, 0.05, 0.0, 0.0), job_dir / GRID_FILE)
        return {}

    return stored_job(data_dir, write)


# ---- the service and what it costs --------------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def lidarmap_serve(data_dir: Path, **settings: object) -> Iterator[tuple[str, psutil.Process]]:
    """``lidarmap serve`` on a free loopback port with ``LIDARMAP_<NAME>`` settings; stopped afterwards."""
    port = free_port()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "LIDARMAP_DATA_DIR": str(data_dir),
           **{f"LIDARMAP_{k.upper()}": str(v) for k, v in settings.items()}}
    server = subprocess.Popen([sys.executable, "-m", "lidarmap.cli", "serve", "--port", str(port)], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while True:
            if server.poll() is not None:
                raise RuntimeError(f"the service exited with {server.returncode}")
            try:
                if httpx.get(f"{url}/healthz", timeout=2.0).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError("the service did not answer /healthz in 120 s")
            time.sleep(0.1)
        yield url, psutil.Process(server.pid)
    finally:
        server.terminate()
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


@dataclass
class Cost:
    """What an attack cost the API process: resident memory before and at its peak [bytes], the
    slowest /healthz answer meanwhile [s], the attack's wall time [s] and the statuses it got."""

    rss_before: int = 0
    rss_peak: int = 0
    healthz_max_s: float = 0.0
    seconds: float = 0.0
    statuses: tuple[int, ...] = ()


def measure(url: str, process: psutil.Process, attack: Callable[[], list[int]]) -> Cost:
    """Run ``attack`` (returning its statuses) while sampling the API's RSS and timing /healthz."""
    cost = Cost(rss_before=process.memory_info().rss)
    cost.rss_peak = cost.rss_before
    stop = threading.Event()

    def sample() -> None:
        while not stop.is_set():
            try:
                cost.rss_peak = max(cost.rss_peak, process.memory_info().rss)
            except psutil.Error:
                return
            stop.wait(0.02)

    def poll() -> None:
        with httpx.Client(timeout=300) as client:
            while not stop.is_set():
                start = time.monotonic()
                with suppress(httpx.HTTPError):
                    client.get(f"{url}/healthz")
                cost.healthz_max_s = max(cost.healthz_max_s, time.monotonic() - start)
                stop.wait(0.05)

    threads = [threading.Thread(target=sample, daemon=True), threading.Thread(target=poll, daemon=True)]
    for thread in threads:
        thread.start()
    start = time.monotonic()
    try:
        cost.statuses = tuple(attack())
    finally:
        cost.seconds = time.monotonic() - start
        stop.set()
        for thread in threads:
            thread.join()
    return cost


def concurrently(requests: list[Callable[[], int]]) -> list[int]:
    """Run the requests at once; their statuses."""
    with ThreadPoolExecutor(len(requests)) as pool:
        return list(pool.map(lambda request: request(), requests))


def tile_requests(url: str, job_id: str, tiles: list[tuple[int, int, int]]) -> list[Callable[[], int]]:
    """One request per occupancy tile (z, x, y)."""

    def one(z: int, x: int, y: int) -> int:
        with httpx.Client(timeout=600) as client:
            return client.get(f"{url}/v1/jobs/{job_id}/tiles/occupancy/{z}/{x}/{y}.png").status_code

    return [lambda z=z, x=x, y=y: one(z, x, y) for z, x, y in tiles]


def trajectory_requests(url: str, job_id: str, method: str, count: int, route: str = "trajectory"
                        ) -> list[Callable[[], int]]:
    """``count`` requests of the JSON trajectory (each reads its whole answer)."""

    def one() -> int:
        with httpx.Client(timeout=600) as client:
            return client.request(method, f"{url}/v1/jobs/{job_id}/{route}").status_code

    return [one] * count
