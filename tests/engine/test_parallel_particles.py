"""The per-particle work (scan matching, map insertion) runs in numba threads with exactly the
results of one thread; ``LIDARMAP_THREADS`` sets the thread count."""

from __future__ import annotations

import numba
import numpy as np
import pytest
from ci_skips import skip_or_fail_on_ci
from log_helpers import first_scans

from slam_engine.config import SlamConfig
from slam_engine.errors import ConfigError
from slam_engine.formats import load_log
from slam_engine.frontend.grid import ParticleGrids
from slam_engine.frontend.particle_filter import engine_threads
from slam_engine.frontend.raycast import insert_scan
from slam_engine.pipeline import run_slam

N_SCANS = 150


def test_threads_give_bit_identical_trajectory_and_map(dataset, monkeypatch) -> None:
    if numba.config.NUMBA_NUM_THREADS < 2:
        skip_or_fail_on_ci("needs at least 2 numba threads (NUMBA_NUM_THREADS=2 gives them on one core)")
    log = first_scans(load_log(dataset("benchmark/intel.clf")), N_SCANS)
    results = {}
    for threads in ("1", "2"):
        monkeypatch.setenv("LIDARMAP_THREADS", threads)
        results[threads] = run_slam(log, SlamConfig(particles=12, seed=3))
        assert numba.get_num_threads() == int(threads)
    one, two = results["1"], results["2"]
    assert one.scan_stats.resampled.any()  # copy-on-write tiles were shared and privatized on this run
    assert np.array_equal(one.trajectory.poses, two.trajectory.poses)
    assert np.array_equal(one.scan_stats.n_eff, two.scan_stats.n_eff)
    assert np.array_equal(one.scan_stats.match_score, two.scan_stats.match_score)
    assert one.grid.log_odds.shape == two.grid.log_odds.shape
    assert np.array_equal(one.grid.log_odds, two.grid.log_odds)
    assert (one.grid.origin_x_m, one.grid.origin_y_m) == (two.grid.origin_x_m, two.grid.origin_y_m)


def test_thread_count_from_environment(monkeypatch) -> None:
    monkeypatch.delenv("LIDARMAP_THREADS", raising=False)
    assert engine_threads() == numba.config.NUMBA_NUM_THREADS
    monkeypatch.setenv("LIDARMAP_THREADS", "1")
    assert engine_threads() == 1
    monkeypatch.setenv("LIDARMAP_THREADS", "9999")
    assert engine_threads() == numba.config.NUMBA_NUM_THREADS  # capped at what numba has
    for bad in ("0", "two", "-3"):
        monkeypatch.setenv("LIDARMAP_THREADS", bad)
        with pytest.raises(ConfigError, match="LIDARMAP_THREADS"):
            engine_threads()


def test_insert_refuses_repeated_particles() -> None:
    # two threads would write one map: refused instead of racing
    grids = ParticleGrids(2, 0.1)
    with pytest.raises(ValueError, match="distinct"):
        insert_scan(grids, np.zeros((2, 3)), np.zeros(2), np.array([[1.0, 0.0]]), np.array([True]),
                    0.9, -0.4, -5.0, 5.0, particles=np.array([1, 1]))
