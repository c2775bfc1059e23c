"""SE(2) pose algebra on ``[x_m, y_m, theta_rad]`` arrays, vectorised over leading dimensions.

``compose(a, b)`` is the pose ``b`` (expressed in frame ``a``) taken into ``a``'s parent frame:
``T_world_from_b = T_world_from_a @ T_a_from_b``. Angles are wrapped to ``[-pi, pi)``.
"""

from __future__ import annotations

import math

import numpy as np


def wrap_angle(theta_rad: np.ndarray | float) -> np.ndarray | float:
    """Angle(s) wrapped to ``[-pi, pi)`` [rad]."""
    return (np.asarray(theta_rad) + np.pi) % (2.0 * np.pi) - np.pi


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a (+) b``: (..., 3) poses; ``b`` is relative to ``a``."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def place_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 2) the points ``points`` (N, 2) [m], given in the frame of ``pose`` (3,), in the frame
    ``pose`` is given in (e.g. vehicle-frame end points at a world pose: world frame)."""
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    return np.column_stack([pose[0] + c * points[:, 0] - s * points[:, 1],
                            pose[1] + s * points[:, 0] + c * points[:, 1]])


def place_each(poses: np.ndarray, points: np.ndarray, owner: np.ndarray) -> np.ndarray:
    """(N, 2) the points ``points`` (N, 2) [m], point i given in the frame of ``poses[owner[i]]``
    (``poses`` (M, 3)), in the frame the poses are given in: the values :func:`place_points` gives pose
    by pose, in one pass."""
    headings = poses[:, 2].tolist()
    c = np.array([math.cos(t) for t in headings])[owner]
    s = np.array([math.sin(t) for t in headings])[owner]
    return np.column_stack([poses[owner, 0] + c * points[:, 0] - s * points[:, 1],
                            poses[owner, 1] + s * points[:, 0] + c * points[:, 1]])


def key_poses(poses: np.ndarray, spacing_m: float, spacing_rad: float) -> np.ndarray:
    """Indices of ``poses`` (S, 3) kept when each must lie ``spacing_m`` [m] or ``spacing_rad`` [rad] from the
    last kept one (the first is kept): a path thinned as a front end picks its key frames."""
    if len(poses) == 0:
        return np.zeros(0, np.int64)
    kept = [0]
    for k in range(1, len(poses)):
        moved = relative(poses[kept[-1]], poses[k])
        if math.hypot(moved[0], moved[1]) >= spacing_m or abs(moved[2]) >= spacing_rad:
            kept.append(k)
    return np.array(kept, np.int64)


def point_bounds(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lowest (2,) and the highest (2,) coordinates of (N > 0, 2) points, column by column: the same
    values as ``min(axis=0)`` / ``max(axis=0)``, which walk a two-column array row by row (30x slower
    on a million points)."""
    return (np.array([points[:, 0].min(), points[:, 1].min()]),
            np.array([points[:, 0].max(), points[:, 1].max()]))


def inverse(a: np.ndarray) -> np.ndarray:
    """``(-) a``: the pose of the parent frame expressed in ``a`` (..., 3)."""
    a = np.asarray(a, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -c * a[..., 0] - s * a[..., 1]
    y = s * a[..., 0] - c * a[..., 1]
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(-) a (+) b``: pose ``b`` expressed in the frame of pose ``a`` (..., 3)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx = b[..., 0] - a[..., 0]
    dy = b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[..., 2] - a[..., 2])], axis=-1)


def interpolate(t_s: np.ndarray, poses: np.ndarray, t_query_s: np.ndarray) -> np.ndarray:
    """Poses at ``t_query_s`` (M,) by linear interpolation of (N, 3) ``poses`` stamped ``t_s`` (N,),
    the heading along the shorter arc. Queries outside ``[t_s[0], t_s[-1]]`` take the end pose."""
    t_s = np.asarray(t_s, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    t_query_s = np.asarray(t_query_s, dtype=np.float64)
    if len(t_s) == 0:
        raise ValueError("cannot interpolate an empty pose track")
    if len(t_s) == 1:
        return np.repeat(poses[:1], len(t_query_s), axis=0)
    theta = np.unwrap(poses[:, 2])
    out = np.empty((len(t_query_s), 3))
    out[:, 0] = np.interp(t_query_s, t_s, poses[:, 0])
    out[:, 1] = np.interp(t_query_s, t_s, poses[:, 1])
    out[:, 2] = wrap_angle(np.interp(t_query_s, t_s, theta))
    return out


def to_matrix(pose: np.ndarray) -> np.ndarray:
    """(..., 3) poses -> (..., 3, 3) homogeneous 2-D transforms."""
    pose = np.asarray(pose, dtype=np.float64)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    m = np.zeros(pose.shape[:-1] + (3, 3))
    m[..., 0, 0], m[..., 0, 1], m[..., 0, 2] = c, -s, pose[..., 0]
    m[..., 1, 0], m[..., 1, 1], m[..., 1, 2] = s, c, pose[..., 1]
    m[..., 2, 2] = 1.0
    return m


def from_matrix(m: np.ndarray) -> np.ndarray:
    """(..., 3, 3) homogeneous 2-D transforms -> (..., 3) poses."""
    m = np.asarray(m, dtype=np.float64)
    return np.stack([m[..., 0, 2], m[..., 1, 2], np.arctan2(m[..., 1, 0], m[..., 0, 0])], axis=-1)


def to_matrix_4x4(pose: np.ndarray, z_m: float = 0.0) -> np.ndarray:
    """(..., 3) planar poses -> (..., 4, 4) 3-D transforms (rotation about z, height ``z_m``)."""
    pose = np.asarray(pose, dtype=np.float64)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    m = np.zeros(pose.shape[:-1] + (4, 4))
    m[..., 0, 0], m[..., 0, 1], m[..., 0, 3] = c, -s, pose[..., 0]
    m[..., 1, 0], m[..., 1, 1], m[..., 1, 3] = s, c, pose[..., 1]
    m[..., 2, 2], m[..., 2, 3], m[..., 3, 3] = 1.0, z_m, 1.0
    return m


def planar_from_4x4(T: np.ndarray) -> np.ndarray:
    """The planar part [x_m, y_m, yaw_rad] of a (..., 4, 4) transform (yaw from its rotated x axis)."""
    T = np.asarray(T, dtype=np.float64)
    return np.stack([T[..., 0, 3], T[..., 1, 3], np.arctan2(T[..., 1, 0], T[..., 0, 0])], axis=-1)


def is_planar_4x4(T: np.ndarray, tol: float = 1e-6) -> bool:
    """True when a 4x4 transform only rotates about z (no roll or pitch)."""
    T = np.asarray(T, dtype=np.float64)
    return bool(abs(T[2, 2] - 1.0) < tol and np.all(np.abs(T[:2, 2]) < tol) and np.all(np.abs(T[2, :2]) < tol))
