"""A job's memory estimate, from its configuration and log, before it runs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from slam_engine.config import SlamConfig
from slam_engine.evaluation.memory_estimate import BASE_BYTES, estimate_job_memory_bytes, map_extent_m
from slam_engine.simulation import simulate

REPO = Path(__file__).resolve().parents[2]

# Maps a short simulated drive and writes every product, in a fresh process; prints the estimate
# and the process's peak resident memory.
MEASURE = """
import json, sys, tempfile
from slam_engine.config import SlamConfig
from slam_engine.evaluation.memory_estimate import estimate_job_memory_bytes, peak_resident_bytes
from slam_engine.pipeline import run_slam
from slam_engine.products import write_products
from slam_engine.simulation import simulate
log = simulate("office", seed=1, rig="robot", max_duration_s=20.0).log
config = SlamConfig(particles=10, snapshot_every_scans=10)
estimate = estimate_job_memory_bytes(config, log)
write_products(run_slam(log, config), tempfile.mkdtemp())
print(json.dumps({"estimate": estimate, "peak": peak_resident_bytes()}))
"""


def test_estimate_grows_with_particles_and_finer_cells() -> None:
    log = simulate("office", seed=0, rig="robot", max_duration_s=10.0).log
    base = estimate_job_memory_bytes(SlamConfig(), log)
    assert base > BASE_BYTES
    assert estimate_job_memory_bytes(SlamConfig(particles=300), log) > base
    assert estimate_job_memory_bytes(SlamConfig(grid={"resolution_m": 0.025}), log) > 2 * (base - BASE_BYTES)
    width, height = map_extent_m(log, SlamConfig())
    assert 5.0 < width < 200.0 and 5.0 < height < 200.0


def test_estimate_covers_the_measured_peak_of_a_run() -> None:
    # kernels compiled (or loaded) by a process of their own first: compiling takes memory that no
    # job pays once the set-up has filled the cache, and a cache invalidated meanwhile would count it
    warm = subprocess.run([sys.executable, "-m", "slam_engine.kernels"], cwd=REPO, capture_output=True, text=True,
                          timeout=600)
    assert warm.returncode == 0, warm.stderr
    done = subprocess.run([sys.executable, "-c", MEASURE], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    assert figures["peak"] <= figures["estimate"] <= 3 * figures["peak"], figures


def test_a_process_peak_is_its_own_not_its_parents() -> None:
    # Linux counts a parent's resident size at fork/exec into the child's ru_maxrss: a small run
    # started from a large test session seemed to peak at the session's size (770 MB in CI)
    ballast = np.ones(300 * 1024**2 // 8)  # this process: 300 MB more resident
    probe = ("import resource; from slam_engine.evaluation.memory_estimate import peak_resident_bytes; "
             "print(peak_resident_bytes(), resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)")
    done = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, timeout=300)
    del ballast
    assert done.returncode == 0, done.stderr
    own, rusage = (int(v) for v in done.stdout.split())
    assert own < 250 * 1024**2, (own, rusage)
