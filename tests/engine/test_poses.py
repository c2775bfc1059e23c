"""SE(2) pose algebra: composition, inverse, relative poses, interpolation, matrices."""

from __future__ import annotations

import numpy as np

from slam_engine.model.poses import (
    compose,
    from_matrix,
    interpolate,
    inverse,
    is_planar_4x4,
    place_each,
    place_points,
    planar_from_4x4,
    point_bounds,
    relative,
    to_matrix,
    to_matrix_4x4,
    wrap_angle,
)


def test_compose_hand_computed() -> None:
    a = np.array([1.0, 2.0, np.pi / 2])
    b = np.array([1.0, 0.0, np.pi / 2])
    # moving 1 m forward while facing +y lands at (1, 3); headings add up to pi
    np.testing.assert_allclose(compose(a, b), [1.0, 3.0, -np.pi], atol=1e-12)


def test_inverse_and_relative_round_trip() -> None:
    rng = np.random.default_rng(1)
    a = rng.uniform(-5, 5, (20, 3))
    b = rng.uniform(-5, 5, (20, 3))
    np.testing.assert_allclose(compose(a, inverse(a)), np.zeros((20, 3)), atol=1e-12)
    np.testing.assert_allclose(compose(a, relative(a, b))[:, :2], b[:, :2], atol=1e-12)
    np.testing.assert_allclose(wrap_angle(compose(a, relative(a, b))[:, 2] - b[:, 2]), 0.0, atol=1e-12)


def test_matrices_agree_with_compose() -> None:
    a = np.array([0.5, -1.0, 0.3])
    b = np.array([2.0, 1.0, -1.2])
    np.testing.assert_allclose(from_matrix(to_matrix(a) @ to_matrix(b)), compose(a, b), atol=1e-12)
    T = to_matrix_4x4(a, z_m=0.7)
    assert T[2, 3] == 0.7 and is_planar_4x4(T)
    np.testing.assert_allclose(planar_from_4x4(T), a, atol=1e-12)
    tilted = T.copy()
    roll = np.array([[1, 0, 0], [0, np.cos(0.2), -np.sin(0.2)], [0, np.sin(0.2), np.cos(0.2)]])
    tilted[:3, :3] = tilted[:3, :3] @ roll
    assert not is_planar_4x4(tilted)


def test_interpolate_takes_the_short_way_round_pi() -> None:
    t = np.array([0.0, 1.0])
    poses = np.array([[0.0, 0.0, np.pi - 0.1], [2.0, 4.0, -np.pi + 0.1]])
    mid = interpolate(t, poses, np.array([0.5, -1.0, 2.0]))
    np.testing.assert_allclose(mid[0, :2], [1.0, 2.0])
    assert abs(abs(mid[0, 2]) - np.pi) < 1e-9  # through pi, not through 0
    np.testing.assert_allclose(mid[1], poses[0])  # clamped before the start
    np.testing.assert_allclose(mid[2, :2], poses[1, :2])  # clamped after the end


def test_placing_point_sets_at_once_equals_placing_them_one_by_one() -> None:
    """place_each: every point at its own set's pose, bit for bit what place_points gives set by set."""
    rng = np.random.default_rng(4)
    poses = rng.uniform(-20, 20, (7, 3))
    sets = [rng.uniform(-30, 30, (n, 2)) for n in (5, 0, 12, 1, 30, 8, 3)]
    owner = np.repeat(np.arange(7), [len(p) for p in sets])
    together = place_each(poses, np.concatenate(sets), owner)
    assert np.array_equal(together, np.concatenate([place_points(p, q) for p, q in zip(poses, sets, strict=True)]))
    every_third = place_each(poses, np.concatenate(sets)[::3], owner[::3])
    assert np.array_equal(every_third, together[::3])


def test_point_bounds_are_the_columns_extremes() -> None:
    points = np.random.default_rng(5).normal(0.0, 10.0, (1001, 2))
    low, high = point_bounds(points)
    assert np.array_equal(low, points.min(axis=0)) and np.array_equal(high, points.max(axis=0))
    assert np.array_equal(point_bounds(np.array([[1.0, -2.0]]))[1], [1.0, -2.0])
