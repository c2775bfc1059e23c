"""SE(2) pose algebra: composition, inverse, relative poses, interpolation, matrices."""

from __future__ import annotations

import numpy as np

from slam_engine.poses import (
    compose,
    from_matrix,
    interpolate,
    inverse,
    is_planar_4x4,
    planar_from_4x4,
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
