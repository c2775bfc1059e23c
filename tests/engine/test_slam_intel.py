"""End to end on the Intel Research Lab benchmark (real scans, re-created odometry)."""

from __future__ import annotations

import numpy as np
import pytest
from log_helpers import first_scans

from slam_engine.config import SlamConfig
from slam_engine.evaluation.metrics import Relations, read_relations, relation_errors
from slam_engine.formats import load_log
from slam_engine.pipeline import run_slam

N_SCANS = 300  # the first third of the log (about 160 m, with loops), to keep the test short


def _relations_until(relations: Relations, t_end: float) -> Relations:
    keep = (relations.t1_s <= t_end) & (relations.t2_s <= t_end)
    return Relations(relations.t1_s[keep], relations.t2_s[keep], relations.motion[keep])


@pytest.mark.slow
def test_intel_slam_is_far_better_than_dead_reckoning(dataset) -> None:
    log = first_scans(load_log(dataset("benchmark/intel.clf")), N_SCANS)
    relations = _relations_until(read_relations(dataset("benchmark/intel.relations")), log.scans.t_s[-1])
    result = run_slam(log, SlamConfig(particles=10, seed=0))

    assert len(result.trajectory) == N_SCANS and len(result.dead_reckoning) == N_SCANS
    slam = relation_errors(result.trajectory, relations)
    dead = relation_errors(result.dead_reckoning, relations)
    assert slam.all.n_failed == 0
    # measured: SLAM 0.024 m / 0.40 deg, dead reckoning 1.2 m / 11 deg on this part
    assert slam.all.trans_mean_m < 0.06
    assert slam.all.rot_mean_deg < 1.0
    assert slam.all.trans_mean_m < dead.all.trans_mean_m / 10
    # the walls are in the map where the scans see them: the returns of the scan at every 50th pose
    # fall within one 5 cm cell of an occupied cell
    grid = result.grid
    angles = log.lidar.beam_angles_rad
    for k in range(0, N_SCANS, 50):
        x, y, theta = result.trajectory.poses[k]
        r = log.scans.ranges_m[k]
        ok = np.isfinite(r) & (r < 20.0)
        ix, iy = grid.world_to_cell(x + r[ok] * np.cos(theta + angles[ok]), y + r[ok] * np.sin(theta + angles[ok]))
        near_wall = np.max([grid.log_odds[iy + a, ix + b] for a in (-1, 0, 1) for b in (-1, 0, 1)], axis=0) > 0
        assert np.mean(near_wall) > 0.8  # measured 0.88-1.0 (people walk through the lab)
