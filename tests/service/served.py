"""A real ``lidarmap serve`` in its own process, for the tests that measure the API process itself
(its memory, its answers to raw sockets): yields its URL and its process."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import psutil

ROOT = Path(__file__).resolve().parents[2]
STARTUP_LIMIT_S = 120.0


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
                              stdout=subprocess.DEVNULL)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + STARTUP_LIMIT_S
        while True:
            assert server.poll() is None, f"the service exited with {server.returncode}"
            try:
                if httpx.get(f"{url}/healthz", timeout=2.0).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert time.monotonic() < deadline, f"the service did not answer /healthz in {STARTUP_LIMIT_S} s"
            time.sleep(0.1)
        yield url, psutil.Process(server.pid)
    finally:
        server.terminate()
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


class PeakRss:
    """Samples a process's resident size [bytes] every ``every_s`` in a thread; ``peak`` is the largest."""

    def __init__(self, process: psutil.Process, every_s: float = 0.02):
        self.process, self.every_s, self.peak = process, every_s, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.peak = max(self.peak, self.process.memory_info().rss)
            except psutil.Error:
                return
            self._stop.wait(self.every_s)

    def __enter__(self) -> PeakRss:
        self.peak = self.process.memory_info().rss
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
