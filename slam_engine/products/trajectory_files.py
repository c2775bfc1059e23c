"""Trajectory files: lidarmap JSON and TUM, written and read back.

lidarmap JSON (``trajectory.json``, ``dead_reckoning.json``)::

    {"format": "lidarmap-trajectory", "version": 2,
     "frame": "map",                      # what the poses are expressed in
     "units": {"t_s": "s", "x_m": "m", "y_m": "m", "theta_rad": "rad"},
     "config": {...} | null,              # the SlamConfig used (model_dump), when known
     "poses": [{"t_s": 12.5, "x_m": 0.0, "y_m": 0.0, "theta_rad": 0.0}, ...]}

The pose fields are named as the API's poses are (unit-suffixed). ``read_trajectory`` also accepts a
bare JSON list of such pose objects, and the names of version 1 files (``t, x, y, theta``, written
before version 2) for each field, so the trajectories of older jobs still load.

TUM (``trajectory.tum``): one line per pose, ``t x y z qx qy qz qw`` (seconds, metres, unit
quaternion), ``#`` comments allowed; the format evo and the TUM RGB-D tools read. A planar pose
is written with z = 0 and a rotation about z by theta; on reading, theta is the yaw of the quaternion.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from slam_engine.errors import TrajectoryFormatError
from slam_engine.model.result import Trajectory
from slam_engine.products.files import atomic_path, write_text_atomic

JSON_FORMAT_NAME = "lidarmap-trajectory"
JSON_VERSION = 2  # version 1 named the pose fields t, x, y, theta
POSE_FIELDS = ("t_s", "x_m", "y_m", "theta_rad")
POSE_FIELD_ALIASES = {"t_s": "t", "x_m": "x", "y_m": "y", "theta_rad": "theta"}  # version 1's names
_JSON_EXPECTED = ("expected lidarmap trajectory JSON: an object with a 'poses' list (or a list) of "
                  "{\"t_s\", \"x_m\", \"y_m\", \"theta_rad\"} numbers (or version 1's \"t\", \"x\", \"y\", "
                  "\"theta\")")
_TUM_EXPECTED = "expected TUM trajectory: 8 numbers per line 't x y z qx qy qz qw'"


def write_trajectory_json(traj: Trajectory, path: str | Path, frame: str = "map",
                          config: dict | None = None) -> Path:
    """Write ``traj`` as lidarmap JSON (see module docstring); returns the path."""
    poses = [{"t_s": float(t), "x_m": float(p[0]), "y_m": float(p[1]), "theta_rad": float(p[2])}
             for t, p in zip(traj.t_s, traj.poses, strict=True)]
    document = {"format": JSON_FORMAT_NAME, "version": JSON_VERSION, "frame": frame,
                "units": {"t_s": "s", "x_m": "m", "y_m": "m", "theta_rad": "rad"},
                "config": config, "poses": poses}
    return write_text_atomic(path, json.dumps(document, indent=1, allow_nan=False) + "\n")


def write_trajectory_tum(traj: Trajectory, path: str | Path) -> Path:
    """Write ``traj`` in TUM format ``t x y z qx qy qz qw``; returns the path."""
    n = len(traj)
    # a rotation about z by theta: (0, 0, sin(theta / 2), cos(theta / 2)), as scipy's Rotation gives it
    half = traj.poses[:, 2] / 2.0
    quat_xyzw = np.column_stack([np.zeros(n), np.zeros(n), np.sin(half), np.cos(half)])
    table = np.column_stack([traj.t_s, traj.poses[:, 0], traj.poses[:, 1], np.zeros(n), quat_xyzw])
    with atomic_path(path) as tmp:
        np.savetxt(tmp, table, fmt="%.9f", header="t x y z qx qy qz qw (s, m, unit quaternion)")
    return Path(path)


def read_trajectory(path: str | Path, format: str = "auto") -> Trajectory:
    """Read a lidarmap JSON or TUM trajectory. ``format``: ``"auto"`` (JSON when the file starts
    with ``{`` or ``[``, TUM otherwise), ``"json"`` or ``"tum"``.

    Raises :class:`TrajectoryFormatError` naming the file, the line or pose, and the expected format.
    """
    path = Path(path)
    if format not in ("auto", "json", "tum"):
        raise TrajectoryFormatError(f"unknown trajectory format {format!r}; use auto, json or tum", path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise TrajectoryFormatError("file not found", path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise TrajectoryFormatError(f"cannot read: {exc}", path) from None
    if format == "auto":
        format = "json" if text.lstrip()[:1] in ("{", "[") else "tum"
    return _parse_json(text, path) if format == "json" else _parse_tum(text, path)


def _parse_json(text: str, path: Path) -> Trajectory:
    try:
        document = json.loads(text)
    except json.JSONDecodeError as exc:
        raise TrajectoryFormatError(f"not valid JSON ({exc.msg}); {_JSON_EXPECTED}", path,
                                    f"line {exc.lineno}") from None
    poses = document.get("poses") if isinstance(document, dict) else document
    if not isinstance(poses, list):
        raise TrajectoryFormatError(f"no 'poses' list; {_JSON_EXPECTED}", path)
    rows = np.empty((len(poses), 4))
    for i, pose in enumerate(poses):
        try:
            rows[i] = [float(pose[key] if key in pose else pose[POSE_FIELD_ALIASES[key]]) for key in POSE_FIELDS]
        except (KeyError, TypeError, ValueError):
            raise TrajectoryFormatError(f"bad pose {pose!r}; {_JSON_EXPECTED}", path, f"poses[{i}]") from None
        if not np.all(np.isfinite(rows[i])):
            raise TrajectoryFormatError("non-finite value", path, f"poses[{i}]")
    return _checked_trajectory(rows[:, 0], rows[:, 1:], path)


def _parse_tum(text: str, path: Path) -> Trajectory:
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = stripped.replace(",", " ").split()
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise TrajectoryFormatError(f"non-numeric field; {_TUM_EXPECTED}", path, f"line {lineno}") from None
        if len(values) != 8:
            raise TrajectoryFormatError(f"{len(values)} fields; {_TUM_EXPECTED}", path, f"line {lineno}")
        if not all(math.isfinite(v) for v in values):
            raise TrajectoryFormatError("non-finite value", path, f"line {lineno}")
        if np.linalg.norm(values[4:]) < 1e-9:
            raise TrajectoryFormatError("zero quaternion", path, f"line {lineno}")
        rows.append(values)
    if not rows:
        return _checked_trajectory(np.zeros(0), np.zeros((0, 3)), path)
    from scipy.spatial.transform import Rotation  # ~26 MB: imported only to read TUM files

    table = np.array(rows)
    yaw = Rotation.from_quat(table[:, 4:8]).as_euler("ZYX")[:, 0]
    return _checked_trajectory(table[:, 0], np.column_stack([table[:, 1], table[:, 2], yaw]), path)


def _checked_trajectory(t_s: np.ndarray, poses: np.ndarray, path: Path) -> Trajectory:
    decreasing = np.flatnonzero(np.diff(t_s) < 0)
    if decreasing.size:
        raise TrajectoryFormatError("timestamps go backwards", path, f"pose {int(decreasing[0]) + 1}")
    return Trajectory(t_s=np.asarray(t_s, dtype=np.float64), poses=np.asarray(poses, dtype=np.float64))
