"""``python -m bench.api_attacks``: the API process under the adversarial requests of issue 41, against
a real ``lidarmap serve``: cold tiles of huge grids, concurrent HEAD and GET of a long trajectory, a
huge request header. Prints, per attack, the API process's peak resident memory and the slowest
``/healthz`` answer while it ran (targets: <= 600 MB, <= 1 s).

The huge grids: an 8000 x 8000 grid (244 MB) written into the data folder, as the worker writes it and
as earlier versions did; and the probe's own, a log of three scans 400 m apart mapped through the API
with ``{"particles": 1}``. The long trajectory is a finished job of 400 000 poses written into the data
folder before the service starts (mapping 400 000 scans would take an hour)."""

from __future__ import annotations

import math
import os
import socket
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import psutil

from bench.serve_process import free_port, lidarmap_serve  # noqa: F401  (tests import them from here)

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


def cold_tiles(url: str, job_id: str) -> list[tuple[int, int, int]]:
    """Ten tiles nobody asked for yet: zoom 0 four times (it pools the whole map), then tiles of zoom 1,
    of the middle zoom and of the deepest (native) zoom, in corners and the middle."""
    scheme = httpx.get(f"{url}/v1/jobs/{job_id}/tiles/occupancy", timeout=60).raise_for_status().json()
    top = scheme["max_zoom"]

    def counts(z: int) -> tuple[int, int]:
        span = 256 * 2 ** (top - z)
        return math.ceil(scheme["width_cells"] / span), math.ceil(scheme["height_cells"] / span)

    picks = [(0, 0, 0)] * 4
    for z in (min(1, top), top // 2, top):
        nx, ny = counts(z)
        picks += [(z, nx - 1, ny - 1), (z, nx // 2, ny // 2)]
    return picks


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


# ---- the attacks --------------------------------------------------------------------------------------


def three_far_scans_log() -> bytes:
    """The probe's log: three scans 400 m apart (a 400 x 400 m map from 540 beams)."""
    lines = [b"PARAM robot_front_laser_max 50.0"]
    for i, (x, y) in enumerate([(0.0, 0.0), (400.0, 0.0), (400.0, 400.0)]):
        ranges = " ".join(["5.000"] * 180)
        t = 1.0 + i
        lines.append(f"ODOM {x} {y} 0.0 0 0 0 {t:.6f} bench {t:.6f}".encode())
        lines.append(f"FLASER 180 {ranges} {x} {y} 0.0 {x} {y} 0.0 {t + 0.01:.6f} bench {t + 0.01:.6f}".encode())
    return b"\n".join(lines) + b"\n"


def huge_grid_by_slam(url: str, timeout_s: float = 1800.0) -> str:
    """Map the three far scans with one particle through the API; the finished job's id."""
    with httpx.Client(base_url=url, timeout=120) as client:
        sid = client.post("/v1/sessions", json={"name": "three far scans"}).raise_for_status().json()["id"]
        client.post(f"/v1/sessions/{sid}/logs", files={"file": ("far.clf", three_far_scans_log())}).raise_for_status()
        job = client.post(f"/v1/sessions/{sid}/jobs", json={"particles": 1}).raise_for_status().json()
        deadline = time.monotonic() + timeout_s
        while job["status"] not in ("succeeded", "failed", "cancelled"):
            if time.monotonic() > deadline:
                raise RuntimeError(f"the job did not finish in {timeout_s:g} s")
            time.sleep(1.0)
            job = client.get(f"/v1/jobs/{job['id']}").json()
        if job["status"] != "succeeded":
            raise RuntimeError(f"the job {job['status']}: {job.get('error')}")
        return job["id"]


def header_request(url: str, header_bytes: int) -> list[int]:
    """One GET /healthz whose one header is ``header_bytes`` long; its status (0: no answer)."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=600) as conn:
        conn.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: ")
        block = b"a" * MB
        try:
            for _ in range(header_bytes // MB):
                conn.sendall(block)
            conn.sendall(b"\r\n\r\n")
        except OSError:
            pass  # answered and closed early
        answer = conn.recv(64)
    return [int(answer.split()[1])] if answer.startswith(b"HTTP/") else [0]


def main(poses: int = 400_000, header_mb: int = 64, tiles: bool = True, grid_cells: int = 8000
         ) -> list[tuple[str, Cost]]:
    """Run every attack against a fresh ``lidarmap serve``; print and return the table."""
    rows: list[tuple[str, Cost]] = []
    with tempfile.TemporaryDirectory(prefix="lidarmap-attacks-") as tmp:
        data_dir = Path(tmp) / "data"
        trajectory_job = long_trajectory_job(data_dir, poses)
        big_grids = {"as the worker writes it": grid_job(data_dir, grid_cells),
                     "a plain .npz of an earlier version (converted once)": grid_job(data_dir, grid_cells, True)}
        with lidarmap_serve(data_dir) as (url, process):
            for how, job_id in big_grids.items():
                rows.append((f"10 cold tiles of a {grid_cells} x {grid_cells} grid "
                             f"({grid_cells**2 * 4 / MB:.0f} MB of float32), {how}",
                             measure(url, process, lambda j=job_id: concurrently(
                                 tile_requests(url, j, cold_tiles(url, j))))))
            if tiles:
                grid_job_id = huge_grid_by_slam(url)
                scheme = httpx.get(f"{url}/v1/jobs/{grid_job_id}/tiles/occupancy", timeout=60).json()
                cells = scheme["width_cells"] * scheme["height_cells"]
                cold = cold_tiles(url, grid_job_id)
                rows.append((f"10 cold tiles of a {scheme['width_cells']} x {scheme['height_cells']} grid "
                             f"({cells * 4 / MB:.0f} MB of float32; 3 scans 400 m apart, 1 particle)",
                             measure(url, process, lambda: concurrently(tile_requests(url, grid_job_id, cold)))))
            for method, count in (("HEAD", 8), ("GET", 8)):
                rows.append((f"{count} x {method} trajectory, {poses} poses", measure(
                    url, process, lambda m=method, c=count: concurrently(
                        trajectory_requests(url, trajectory_job, m, c)))))
            rows.append((f"8 x HEAD dead-reckoning, {poses} poses", measure(
                url, process, lambda: concurrently(trajectory_requests(url, trajectory_job, "HEAD", 8,
                                                                       route="dead-reckoning")))))
            rows.append((f"one {header_mb} MB header", measure(url, process,
                                                               lambda: header_request(url, header_mb * MB))))
    print("| attack | statuses | API RSS before [MB] | API peak RSS [MB] | slowest /healthz [s] | wall [s] |")
    print("|---|---|---:|---:|---:|---:|")
    for name, cost in rows:
        statuses = ", ".join(f"{n} x {s}" for s, n in sorted(
            {s: cost.statuses.count(s) for s in cost.statuses}.items()))
        print(f"| {name} | {statuses} | {cost.rss_before / MB:.0f} | {cost.rss_peak / MB:.0f} | "
              f"{cost.healthz_max_s:.2f} | {cost.seconds:.1f} |")
    return rows


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=400_000, help="poses of the long trajectory")
    parser.add_argument("--header-mb", type=int, default=64, help="size of the huge header [MB]")
    parser.add_argument("--grid-cells", type=int, default=8000, help="side of the written square grid [cells]")
    parser.add_argument("--no-slam", action="store_true", help="skip the grid mapped from three far scans")
    args = parser.parse_args()
    main(args.poses, args.header_mb, tiles=not args.no_slam, grid_cells=args.grid_cells)
