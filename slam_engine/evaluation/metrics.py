"""Accuracy of a trajectory: relation errors (Kuemmerle et al. 2009) and absolute trajectory error.

The metric is the one in the benchmark's README (``datasets/benchmark/README.md``):

- a *relation* is the ground-truth motion ``(x_m, y_m, yaw_rad)`` from the pose at ``t1`` to the pose at
  ``t2``, expressed in the frame of the pose at ``t1``;
- the estimate is scored on the poses whose timestamps lie within ``time_tolerance_s`` of ``t1`` and
  ``t2`` (the nearest one); a relation with a missing pose is *failed*: counted and reported, never
  silently dropped;
- translational error = length of the difference of the two relative translations (both in the
  relation's frame), rotational error = absolute wrapped difference of the two relative angles;
- mean and n-1 standard deviation over all relations, and over the *local* (``t2 - t1 <= 30 s``,
  consecutive scans in the benchmark files) and *loop* (``t2 - t1 > 30 s``) subsets.

The absolute trajectory error is the RMSE of positions after the best rigid 2-D alignment
(rotation + translation, no scale) of the estimate onto the ground truth, poses matched by timestamp.

Only numpy here; reading the two text formats raises :class:`LogFormatError` naming file and line.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam_engine.errors import LogFormatError
from slam_engine.model.poses import relative, wrap_angle
from slam_engine.model.result import Trajectory

DEFAULT_TIME_TOLERANCE_S = 0.1
LOOP_MIN_GAP_S = 30.0


@dataclass
class Relations:
    """Ground-truth relative motions: ``t1_s``, ``t2_s`` (N,) seconds; ``motion`` (N, 3)
    [x_m, y_m, yaw_rad] of the pose at t2 expressed in the frame of the pose at t1."""

    t1_s: np.ndarray
    t2_s: np.ndarray
    motion: np.ndarray

    def __len__(self) -> int:
        return int(self.t1_s.shape[0])


@dataclass
class RelationStats:
    """Summary of relation errors over one set of relations.

    ``n_relations`` counts every relation of the set, ``n_failed`` those whose poses were missing
    (excluded from the means, reported here). Means/stds are NaN when too few relations were scored
    (mean needs 1, std needs 2)."""

    n_relations: int
    n_failed: int
    trans_mean_m: float
    trans_std_m: float
    rot_mean_deg: float
    rot_std_deg: float

    @property
    def n_scored(self) -> int:
        return self.n_relations - self.n_failed

    def as_dict(self) -> dict:
        return {"n_relations": self.n_relations, "n_failed": self.n_failed,
                "trans_mean_m": self.trans_mean_m, "trans_std_m": self.trans_std_m,
                "rot_mean_deg": self.rot_mean_deg, "rot_std_deg": self.rot_std_deg}


@dataclass
class RelationMetrics:
    """Relation errors of a trajectory: over ``all`` relations and the ``local`` / ``loop`` subsets,
    plus the per-relation errors (NaN where the relation failed) and the failed relations' times."""

    all: RelationStats
    local: RelationStats
    loop: RelationStats
    trans_errors_m: np.ndarray
    rot_errors_deg: np.ndarray
    failed_t_s: np.ndarray  # (F, 2) [t1, t2] of the failed relations

    # Shortcuts for the numbers everyone quotes.
    @property
    def trans_mean_m(self) -> float:
        return self.all.trans_mean_m

    @property
    def trans_std_m(self) -> float:
        return self.all.trans_std_m

    @property
    def rot_mean_deg(self) -> float:
        return self.all.rot_mean_deg

    @property
    def rot_std_deg(self) -> float:
        return self.all.rot_std_deg

    @property
    def n_failed(self) -> int:
        return self.all.n_failed

    def as_dict(self) -> dict:
        return {"all": self.all.as_dict(), "local": self.local.as_dict(), "loop": self.loop.as_dict(),
                "failed_t_s": self.failed_t_s.tolist()}


# ----------------------------------------------------------------------------------------- reading


def _read_table(path: str | Path, n_columns: int, what: str) -> np.ndarray:
    """Whitespace-separated float rows of ``n_columns`` values; ``#`` comments and blank lines skipped."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise LogFormatError(f"cannot read {what}: {exc.strerror or exc}", path) from exc
    except UnicodeDecodeError as exc:
        raise LogFormatError(f"not a text {what} file (byte {exc.start} is not UTF-8)", path) from None
    rows: list[list[float]] = []
    for line_number, line in enumerate(text.splitlines(), start=1):
        content = line.split("#", 1)[0].strip()
        if not content:
            continue
        fields = content.split()
        if len(fields) != n_columns:
            raise LogFormatError(f"expected {n_columns} values per {what} line, found {len(fields)}",
                                 path, f"line {line_number}")
        try:
            values = [float(field) for field in fields]
        except ValueError as exc:
            raise LogFormatError(f"not a number in {what} line: {exc}", path, f"line {line_number}") from exc
        if not np.all(np.isfinite(values)):
            raise LogFormatError(f"non-finite value in {what} line", path, f"line {line_number}")
        rows.append(values)
    if not rows:
        raise LogFormatError(f"no {what} lines found", path)
    return np.asarray(rows, dtype=np.float64)


def read_relations(path: str | Path) -> Relations:
    """Read a Kuemmerle relations file: ``t1 t2 x y z roll pitch yaw`` per line (s, m, rad).

    2-D only: z, roll and pitch are read and ignored."""
    table = _read_table(path, 8, "relation (t1 t2 x y z roll pitch yaw)")
    return Relations(t1_s=table[:, 0].copy(), t2_s=table[:, 1].copy(),
                     motion=np.ascontiguousarray(table[:, [2, 3, 7]]))


def read_ground_truth(path: str | Path) -> Trajectory:
    """Read a ground-truth file: ``t x y theta`` per line (s, m, m, rad); ``#`` lines are comments.
    Timestamps must increase strictly."""
    table = _read_table(path, 4, "ground-truth pose (t x y theta)")
    steps = np.diff(table[:, 0])
    if np.any(steps <= 0):
        bad = int(np.argmax(steps <= 0)) + 1
        raise LogFormatError(f"timestamps must increase, pose {bad} has t={table[bad, 0]} after "
                             f"t={table[bad - 1, 0]}", path, f"pose {bad}")
    return Trajectory(t_s=table[:, 0].copy(), poses=np.ascontiguousarray(table[:, 1:4]))


def files_beside_log(log_path: str | Path) -> tuple[Path | None, Path | None]:
    """(relations, ground truth) files that come with a log file or log folder, None where absent:
    ``NAME.relations`` (else the only ``*.relations`` in the folder) and ``NAME.gt.txt`` or
    ``ground_truth.txt``, where NAME is the file name without extensions (a folder: its name) and
    the folder is the log's own folder (a folder log: itself)."""
    log_path = Path(log_path)
    folder = log_path if log_path.is_dir() else log_path.parent
    name = log_path.name.split(".", 1)[0] if log_path.is_file() else log_path.name
    own_relations = folder / f"{name}.relations"
    relations: Path | None = own_relations
    if not own_relations.exists():
        candidates = sorted(folder.glob("*.relations"))
        relations = candidates[0] if len(candidates) == 1 else None
    truth = next((p for p in (folder / f"{name}.gt.txt", folder / "ground_truth.txt") if p.exists()), None)
    return relations, truth


# ------------------------------------------------------------------------------------------- maths


def match_times(t_s: np.ndarray, query_s: np.ndarray,
                time_tolerance_s: float = DEFAULT_TIME_TOLERANCE_S) -> np.ndarray:
    """Index into sorted ``t_s`` of the timestamp nearest to each query, or -1 where the nearest is
    further than ``time_tolerance_s``."""
    t_s = np.asarray(t_s, dtype=np.float64)
    query_s = np.asarray(query_s, dtype=np.float64)
    if t_s.size == 0:
        return np.full(query_s.shape, -1, dtype=np.int64)
    if np.any(np.diff(t_s) < 0):
        raise ValueError("trajectory timestamps must be sorted in increasing order")
    right = np.clip(np.searchsorted(t_s, query_s), 0, t_s.size - 1)
    left = np.clip(right - 1, 0, t_s.size - 1)
    nearest = np.where(np.abs(t_s[left] - query_s) <= np.abs(t_s[right] - query_s), left, right)
    return np.where(np.abs(t_s[nearest] - query_s) <= time_tolerance_s, nearest, -1).astype(np.int64)


def _stats(trans_m: np.ndarray, rot_deg: np.ndarray, failed: np.ndarray) -> RelationStats:
    ok = ~failed
    n_ok = int(ok.sum())

    def mean(values: np.ndarray) -> float:
        return float(np.mean(values[ok])) if n_ok >= 1 else float("nan")

    def std(values: np.ndarray) -> float:
        return float(np.std(values[ok], ddof=1)) if n_ok >= 2 else float("nan")

    return RelationStats(n_relations=int(failed.size), n_failed=int(failed.sum()),
                         trans_mean_m=mean(trans_m), trans_std_m=std(trans_m),
                         rot_mean_deg=mean(rot_deg), rot_std_deg=std(rot_deg))


def relation_errors(trajectory: Trajectory, relations: Relations,
                    time_tolerance_s: float = DEFAULT_TIME_TOLERANCE_S,
                    loop_min_gap_s: float = LOOP_MIN_GAP_S) -> RelationMetrics:
    """Relation errors of ``trajectory`` against ground-truth ``relations`` (see module docstring)."""
    i1 = match_times(trajectory.t_s, relations.t1_s, time_tolerance_s)
    i2 = match_times(trajectory.t_s, relations.t2_s, time_tolerance_s)
    failed = (i1 < 0) | (i2 < 0)
    poses = np.asarray(trajectory.poses, dtype=np.float64)
    if poses.shape[0] == 0:
        estimated = np.zeros((len(relations), 3))
    else:
        estimated = relative(poses[np.maximum(i1, 0)], poses[np.maximum(i2, 0)])
    trans_m = np.hypot(estimated[:, 0] - relations.motion[:, 0], estimated[:, 1] - relations.motion[:, 1])
    rot_deg = np.degrees(np.abs(wrap_angle(estimated[:, 2] - relations.motion[:, 2])))
    trans_m[failed] = np.nan
    rot_deg[failed] = np.nan
    is_loop = (relations.t2_s - relations.t1_s) > loop_min_gap_s
    return RelationMetrics(
        all=_stats(trans_m, rot_deg, failed),
        local=_stats(trans_m[~is_loop], rot_deg[~is_loop], failed[~is_loop]),
        loop=_stats(trans_m[is_loop], rot_deg[is_loop], failed[is_loop]),
        trans_errors_m=trans_m, rot_errors_deg=rot_deg,
        failed_t_s=np.stack([relations.t1_s[failed], relations.t2_s[failed]], axis=1))


def align_rigid_2d(source_xy: np.ndarray, target_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (2, 2) and translation t (2,) minimising sum |R @ source + t - target|^2
    (Kabsch/Umeyama without scale, reflections excluded)."""
    source_mean, target_mean = source_xy.mean(axis=0), target_xy.mean(axis=0)
    covariance = (target_xy - target_mean).T @ (source_xy - source_mean)
    u, _, vt = np.linalg.svd(covariance)
    correction = np.diag([1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rotation = u @ correction @ vt
    return rotation, target_mean - rotation @ source_mean


def absolute_trajectory_error(trajectory: Trajectory, ground_truth: Trajectory,
                              time_tolerance_s: float = DEFAULT_TIME_TOLERANCE_S) -> float:
    """RMSE [m] of positions after the best rigid 2-D alignment of ``trajectory`` onto ``ground_truth``.

    Each ground-truth pose is matched to the estimated pose nearest in time (within
    ``time_tolerance_s``); unmatched ground-truth poses are left out. Raises ``ValueError`` when fewer
    than two poses match."""
    index = match_times(trajectory.t_s, ground_truth.t_s, time_tolerance_s)
    matched = index >= 0
    if int(matched.sum()) < 2:
        raise ValueError(f"only {int(matched.sum())} of {len(ground_truth)} ground-truth poses have an "
                         f"estimated pose within {time_tolerance_s} s; cannot align")
    estimate_xy = np.asarray(trajectory.poses, dtype=np.float64)[index[matched], :2]
    truth_xy = np.asarray(ground_truth.poses, dtype=np.float64)[matched, :2]
    rotation, translation = align_rigid_2d(estimate_xy, truth_xy)
    residual = estimate_xy @ rotation.T + translation - truth_xy
    return float(np.sqrt(np.mean(np.sum(residual**2, axis=1))))
