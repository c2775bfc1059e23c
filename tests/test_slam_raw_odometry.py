"""Real raw odometry (no ground truth): the Malaga SENA log's map must have single, consistent walls.

The number: "half agreement" — the walls seen by the first and the second half of the scans, placed
with the trajectory, coincide (within 1.5 cells) for this fraction of cells (bench/map_quality.py).
Doubled or bent walls from a drifting trajectory lower it.
"""

from __future__ import annotations

import numpy as np

from bench.map_quality import half_agreement, occupied_with_neighbour, scan_endpoints_world
from slam_engine.config import SlamConfig
from slam_engine.formats import load_log
from slam_engine.pipeline import run_slam


def test_malaga_walls_agree_between_the_two_halves_of_the_drive(dataset) -> None:
    log = load_log(dataset("malaga/malaga-telecom-one-loop.clf"))
    result = run_slam(log, SlamConfig(particles=10), rng=np.random.default_rng(0))

    slam = half_agreement(scan_endpoints_world(log, result.trajectory, 30.0))
    dead = half_agreement(scan_endpoints_world(log, result.dead_reckoning, 30.0))
    print(f"malaga half agreement: SLAM {slam['half_agreement']:.3f}, dead reckoning {dead['half_agreement']:.3f}")
    assert slam["half_agreement"] > 0.75
    assert slam["half_agreement"] > 2 * dead["half_agreement"]
    assert slam["half_mean_offset_m"] < 0.08
    assert occupied_with_neighbour(result.grid) > 0.8
