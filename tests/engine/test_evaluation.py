"""Relation errors and ATE: hand-computed cases, and the benchmark README's dead-reckoning numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from slam_engine.errors import LogFormatError
from slam_engine.evaluation.metrics import (
    Relations,
    absolute_trajectory_error,
    read_ground_truth,
    read_relations,
    relation_errors,
)
from slam_engine.model.poses import relative
from slam_engine.model.result import Trajectory

# Ground truth: three poses, the last one 39 s after the second (so relations to it are "loop").
GT = Trajectory(t_s=np.array([0.0, 1.0, 40.0]),
                poses=np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, math.pi / 2]]))


def relations_of(truth: Trajectory, pairs: list[tuple[int, int]]) -> Relations:
    i1, i2 = np.array(pairs).T
    return Relations(t1_s=truth.t_s[i1], t2_s=truth.t_s[i2],
                     motion=relative(truth.poses[i1], truth.poses[i2]))


RELATIONS = relations_of(GT, [(0, 1), (1, 2), (0, 2)])


def rigidly_moved(trajectory: Trajectory, angle_rad: float, shift_xy: tuple[float, float]) -> Trajectory:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    xy = trajectory.poses[:, :2] @ np.array([[c, -s], [s, c]]).T + np.asarray(shift_xy)
    return Trajectory(trajectory.t_s.copy(), np.column_stack([xy, trajectory.poses[:, 2] + angle_rad]))


def test_relation_motion_is_in_the_frame_of_the_first_pose():
    np.testing.assert_allclose(RELATIONS.motion, [[1, 0, 0], [0, 1, math.pi / 2], [1, 1, math.pi / 2]],
                               atol=1e-12)


def test_ground_truth_scores_zero():
    metrics = relation_errors(GT, RELATIONS)
    assert metrics.all.n_relations == 3 and metrics.n_failed == 0
    assert metrics.trans_mean_m == pytest.approx(0, abs=1e-12)
    assert metrics.rot_mean_deg == pytest.approx(0, abs=1e-12)
    assert absolute_trajectory_error(GT, GT) == pytest.approx(0, abs=1e-12)


def test_known_perturbation_gives_hand_computed_errors():
    estimate = Trajectory(GT.t_s.copy(), GT.poses.copy())
    estimate.poses[1, :2] = [1.3, 0.4]          # 0.3 / 0.4 off: 0.5 m on both relations touching it
    estimate.poses[2, 2] += 0.2                  # 0.2 rad off on both relations touching it
    metrics = relation_errors(estimate, RELATIONS)
    np.testing.assert_allclose(metrics.trans_errors_m, [0.5, 0.5, 0.0], atol=1e-12)
    rot = math.degrees(0.2)
    np.testing.assert_allclose(metrics.rot_errors_deg, [0.0, rot, rot], atol=1e-12)
    assert metrics.trans_mean_m == pytest.approx(1 / 3)
    assert metrics.trans_std_m == pytest.approx(math.sqrt(1 / 12))  # n-1 std of (0.5, 0.5, 0)
    assert metrics.rot_mean_deg == pytest.approx(2 * rot / 3)
    assert metrics.rot_std_deg == pytest.approx(rot / math.sqrt(3))
    # Local: (0, 1) only; loop: (1, 2) and (0, 2), both more than 30 s apart.
    assert metrics.local.n_relations == 1 and metrics.loop.n_relations == 2
    assert metrics.local.trans_mean_m == pytest.approx(0.5) and metrics.local.rot_mean_deg == pytest.approx(0)
    assert math.isnan(metrics.local.trans_std_m)  # one relation: no n-1 std
    assert metrics.loop.trans_mean_m == pytest.approx(0.25)
    assert metrics.loop.trans_std_m == pytest.approx(math.sqrt(0.125))
    assert metrics.loop.rot_mean_deg == pytest.approx(rot) and metrics.loop.rot_std_deg == pytest.approx(0)


def test_rigid_motion_changes_neither_relations_nor_ate():
    moved = rigidly_moved(GT, 2.5, (10.0, -4.0))
    metrics = relation_errors(moved, RELATIONS)
    assert metrics.trans_mean_m == pytest.approx(0, abs=1e-9)
    assert metrics.rot_mean_deg == pytest.approx(0, abs=1e-9)
    assert absolute_trajectory_error(moved, GT) == pytest.approx(0, abs=1e-9)


def test_ate_hand_computed_stretch():
    truth = Trajectory(np.array([0.0, 1.0]), np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]))
    stretched = Trajectory(np.array([0.0, 1.0]), np.array([[5.0, 5.0, 1.0], [5.0, 9.0, 1.0]]))
    # Best alignment lays the 4 m segment centred on the 2 m one: each end 1 m off.
    assert absolute_trajectory_error(stretched, truth) == pytest.approx(1.0)


def test_missing_pose_counts_as_failed_and_is_reported():
    estimate = Trajectory(GT.t_s[[0, 2]], GT.poses[[0, 2]])
    metrics = relation_errors(estimate, RELATIONS)
    assert metrics.all.n_relations == 3 and metrics.n_failed == 2 and metrics.all.n_scored == 1
    np.testing.assert_allclose(metrics.failed_t_s, [[0.0, 1.0], [1.0, 40.0]])
    assert metrics.local.n_failed == 1 and metrics.loop.n_failed == 1
    assert np.isnan(metrics.trans_errors_m[:2]).all()
    assert metrics.trans_mean_m == pytest.approx(0, abs=1e-12)


def test_time_tolerance_is_0_1_s():
    near = Trajectory(GT.t_s + 0.09, GT.poses.copy())
    far = Trajectory(GT.t_s + 0.11, GT.poses.copy())
    assert relation_errors(near, RELATIONS).n_failed == 0
    assert relation_errors(far, RELATIONS).n_failed == 3
    with pytest.raises(ValueError, match="cannot align"):
        absolute_trajectory_error(far, GT)


def test_bad_files_name_the_line(tmp_path):
    relations = tmp_path / "bad.relations"
    relations.write_text("0 1 0 0 0 0 0 0\n1 2 0.5 0 0 0 0\n")
    with pytest.raises(LogFormatError, match="line 2") as info:
        read_relations(relations)
    assert info.value.path == str(relations)
    truth = tmp_path / "gt.txt"
    truth.write_text("# t x y theta\n0 0 0 0\n1 0 zero 0\n")
    with pytest.raises(LogFormatError, match="line 3"):
        read_ground_truth(truth)
    truth.write_text("1 0 0 0\n0.5 0 0 0\n")
    with pytest.raises(LogFormatError, match="increase"):
        read_ground_truth(truth)


def read_odometry(clf_path) -> Trajectory:
    """Dead reckoning from the ``ODOM x y theta tv rv accel ts host ts`` lines of a CARMEN log."""
    rows = [line.split() for line in clf_path.open() if line.startswith("ODOM ")]
    table = np.array([[float(r[7]), float(r[1]), float(r[2]), float(r[3])] for r in rows])
    return Trajectory(t_s=table[:, 0], poses=table[:, 1:])


@pytest.mark.parametrize("name, trans_m, rot_deg, ate_m, n_relations",
                         [("intel", 6.74, 23.0, 12.2, 1818), ("freiburg-079", 2.79, 16.7, 7.0, 9580)])
def test_dead_reckoning_reproduces_the_readme(dataset, name, trans_m, rot_deg, ate_m, n_relations):
    odometry = read_odometry(dataset(f"benchmark/{name}.clf"))
    relations = read_relations(dataset(f"benchmark/{name}.relations"))
    truth = read_ground_truth(dataset(f"benchmark/{name}.gt.txt"))
    metrics = relation_errors(odometry, relations)
    assert metrics.all.n_relations == n_relations and metrics.n_failed == 0
    assert metrics.local.n_relations == metrics.loop.n_relations == n_relations // 2
    assert round(metrics.trans_mean_m, 2) == trans_m
    assert round(metrics.rot_mean_deg, 1) == rot_deg
    assert round(absolute_trajectory_error(odometry, truth), 1) == ate_m
    # The ground truth scores at the files' rounding (6 decimals).
    exact = relation_errors(truth, relations)
    assert exact.trans_mean_m < 1e-5 and exact.rot_mean_deg < 1e-4
