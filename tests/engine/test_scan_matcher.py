"""The scan matcher recovers a known pose offset on a synthetic room."""

from __future__ import annotations

import numpy as np

from slam_engine.frontend.grid import ParticleGrids
from slam_engine.frontend.raycast import insert_scan
from slam_engine.frontend.scan_matcher import ScanMatcher
from slam_engine.model.poses import compose, relative, wrap_angle

# an 8 m x 6 m room with a pillar and a short wall, so no direction is ambiguous
WALLS = np.array([
    [-4, -3, 4, -3], [4, -3, 4, 3], [4, 3, -4, 3], [-4, 3, -4, -3],
    [1.0, 0.8, 1.6, 0.8], [1.6, 0.8, 1.6, 1.4], [1.6, 1.4, 1.0, 1.4], [1.0, 1.4, 1.0, 0.8],
    [-2.5, -3.0, -2.5, -1.5],
])


def room_scan(pose: np.ndarray, n_beams: int = 360) -> np.ndarray:
    """(n_beams, 2) end points in the vehicle frame of a 360 deg scan taken at ``pose``."""
    angles = np.linspace(-np.pi, np.pi, n_beams, endpoint=False)
    dirs = np.stack([np.cos(angles + pose[2]), np.sin(angles + pose[2])], axis=1)
    best = np.full(n_beams, np.inf)
    for x1, y1, x2, y2 in WALLS:
        seg = np.array([x2 - x1, y2 - y1])
        rhs = np.array([x1 - pose[0], y1 - pose[1]])
        det = dirs[:, 0] * -seg[1] + seg[0] * dirs[:, 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (rhs[0] * -seg[1] + seg[0] * rhs[1]) / det
            u = (dirs[:, 0] * rhs[1] - dirs[:, 1] * rhs[0]) / det
        ok = (np.abs(det) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1)
        best = np.where(ok & (t < best), t, best)
    world = pose[:2] + dirs * best[:, None]
    return relative(pose, np.column_stack([world, np.zeros(n_beams)]))[:, :2]


def _room_map(n_particles: int = 1) -> ParticleGrids:
    grids = ParticleGrids(n_particles, 0.05)
    for pose in ([0.0, 0.0, 0.0], [-1.5, 1.0, 0.7], [2.5, -1.5, -2.0]):
        ends = room_scan(np.array(pose))
        poses = np.tile(pose, (n_particles, 1))
        for _ in range(3):
            insert_scan(grids, poses, np.zeros(2), ends, np.ones(len(ends), bool), 0.9, -0.4, -5.0, 5.0)
    return grids


def test_recovers_a_known_offset_to_sub_cell_accuracy() -> None:
    grids = _room_map(n_particles=4)
    matcher = ScanMatcher(search_xy_m=0.4, search_theta_rad=0.3, min_score=0.3)
    offsets = np.array([[0.15, -0.1, 0.08], [-0.12, 0.14, -0.1], [0.05, 0.05, 0.15], [-0.2, -0.05, 0.0]])
    fits = []
    for truth in (np.array([0.4, -0.3, 0.25]), np.array([-1.0, 0.9, 1.3])):
        start = compose(np.tile(truth, (4, 1)), offsets)
        poses, _, score, accepted = matcher.match(grids, np.arange(4), start, room_scan(truth))
        assert accepted.all() and np.all(score > 0.7)
        # every start converges to the same pose, a map cell's quantisation (< half a cell) from the truth
        assert np.all(np.hypot(poses[:, 0] - truth[0], poses[:, 1] - truth[1]) < 0.04)
        assert np.all(np.abs(wrap_angle(poses[:, 2] - truth[2])) < np.radians(0.3))
        assert np.ptp(poses[:, 0]) < 0.003 and np.ptp(poses[:, 1]) < 0.003
        fits.append(poses)
    # the quantisation is the same shift of the whole map, so the motion between the poses is exact
    true_motion = relative(np.array([0.4, -0.3, 0.25]), np.array([-1.0, 0.9, 1.3]))
    motion = relative(fits[0], fits[1])
    assert np.all(np.hypot(motion[:, 0] - true_motion[0], motion[:, 1] - true_motion[1]) < 0.01)
    assert np.all(np.abs(wrap_angle(motion[:, 2] - true_motion[2])) < np.radians(0.2))


def test_poor_match_falls_back_to_the_prediction() -> None:
    grids = _room_map()
    # a scan from another building: nothing lines up
    scan = np.random.default_rng(0).uniform(-3, 3, (200, 2))
    start = np.array([[0.4, -0.3, 0.25]])
    poses, _, score, accepted = ScanMatcher(0.3, 0.2, min_score=0.6).match(grids, np.arange(1), start, scan)
    assert not accepted[0] and score[0] < 0.6
    np.testing.assert_array_equal(poses, start)


def test_residual_is_lower_at_the_true_pose() -> None:
    grids = _room_map(n_particles=2)
    truth = np.array([0.4, -0.3, 0.25])
    start = np.array([truth, compose(truth, np.array([0.3, 0.0, 0.0]))])
    # zero-size window: every fit is rejected, so the scores are those of the given poses
    _, residual, _, _ = ScanMatcher(0.0, 0.0, 0.0).match(grids, np.arange(2), start, room_scan(truth))
    assert residual[0] < 0.5 * residual[1]
