"""``lidarmap serve`` in its own process on a free loopback port, for benchmarks and tests that need a real
server (its own data folder, ``LIDARMAP_<NAME>`` settings)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import psutil

ROOT = Path(__file__).resolve().parents[1]
STARTUP_S = 120.0  # a bound on the wait for /healthz, not a speed target


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def serving(args: list[str], env: dict[str, str], port: int, quiet: bool = True) -> Iterator[subprocess.Popen]:
    """The server process ``args`` (with ``env``) started and, once its ``/healthz`` on loopback ``port``
    answers, handed over; terminated (killed after 30 s) afterwards. ``quiet``: its output discarded."""
    output = subprocess.DEVNULL if quiet else None
    server = subprocess.Popen(args, env=env, stdout=output, stderr=output)
    try:
        deadline = time.monotonic() + STARTUP_S
        while True:
            if server.poll() is not None:
                raise RuntimeError(f"the service exited with {server.returncode}")
            try:
                if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2.0).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"the service did not answer /healthz in {STARTUP_S:.0f} s")
            time.sleep(0.1)
        yield server
    finally:
        server.terminate()
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


@contextmanager
def lidarmap_serve(data_dir: Path, **settings: object) -> Iterator[tuple[str, psutil.Process]]:
    """``lidarmap serve`` on a free loopback port with its data in ``data_dir`` and ``LIDARMAP_<NAME>``
    settings: (its URL once ``/healthz`` answers, its process); stopped afterwards."""
    port = free_port()
    path = os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])
    env = {**os.environ, "PYTHONPATH": path, "LIDARMAP_DATA_DIR": str(data_dir),
           **{f"LIDARMAP_{k.upper()}": str(v) for k, v in settings.items()}}
    with serving([sys.executable, "-m", "lidarmap.cli", "serve", "--port", str(port)], env, port) as server:
        yield f"http://127.0.0.1:{port}", psutil.Process(server.pid)
