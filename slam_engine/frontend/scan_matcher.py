"""Scan-to-map matching for every particle (numba): a damped Gauss-Newton fit of the scan's end
points onto the particle's own map, coarse to fine.

Score: the map value ``M`` in [0, 1] at each end point, bilinearly interpolated between cell
centres (a smooth function of the pose, so the fit reaches sub-cell accuracy); the fit minimises
``sum (1 - M)^2`` plus a weak prior that keeps the pose near the odometry prediction where the
scan leaves a direction unconstrained (a corridor). It starts on the coarsest map level (cells
``2**3`` times larger: a basin of attraction of tens of centimetres) and refines level by level.
``M`` squashes log-odds ``l`` as ``0.5 + 0.5 l / (1 + |l|)`` (unknown = 0.5, cheap, monotone).

A match is rejected (the caller keeps the odometry proposal) when its mean ``M`` at level 0 is
below a threshold or when it left the search window.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from slam_engine.frontend.grid import LOG_ODDS_UNIT, N_LEVELS, TILE_SHIFT, ParticleGrids, cell_value


def _squash_table() -> np.ndarray:
    """Map value M in [0, 1] of every stored log-odds value (int16, units of ``LOG_ODDS_UNIT``),
    indexed by ``stored + 32768``: M = 0.5 + 0.5 * l / (1 + |l|), a smooth squash of the log-odds l."""
    v = np.arange(-32768, 32768, dtype=np.float64) * LOG_ODDS_UNIT
    return 0.5 + 0.5 * v / (1.0 + np.abs(v))


SQUASH = _squash_table()
SQUASH_OFFSET = 32768  # SQUASH index of stored value 0
PRESEARCH_STEP_RAD = 0.03  # heading step of the coarse correlative search [rad] (~1.7 deg)


@nb.njit(cache=True, nogil=True, inline="always")
def _bilinear_corner(x, y, inv_res):
    """Global indices (i0, j0) of the cell centre left of and below (x, y) [m] on a level of cells
    ``1 / inv_res`` wide, and the fractions (fu, fv) of the way to the next centres. Scalars only:
    an inlined helper that took arrays would cost reference counting at every point."""
    u = x * inv_res - 0.5
    v = y * inv_res - 0.5
    fi = math.floor(u)
    fj = math.floor(v)
    return int(fi), int(fj), u - fi, v - fj


@nb.njit(cache=True, nogil=True, inline="always")
def _bilinear(v00, v10, v01, v11, fu, fv):
    """Bilinear value between four cell values at fractions (fu, fv), and its derivatives along u and v
    [per cell]."""
    m = (1.0 - fv) * ((1.0 - fu) * v00 + fu * v10) + fv * ((1.0 - fu) * v01 + fu * v11)
    return m, (1.0 - fv) * (v10 - v00) + fv * (v11 - v01), (1.0 - fu) * (v01 - v00) + fu * (v11 - v10)


@nb.njit(cache=True, nogil=True, inline="always")
def _squash(squash, stored):
    return squash[stored + SQUASH_OFFSET]


@nb.njit(cache=True, nogil=True, inline="always")
def _sample(squash, pool, tables, p, tile_x0, tile_y0, shift, inv_res, x, y):
    """Bilinear map value M at (x, y) [m] and its gradient [1/m] on one level."""
    i0, j0, fu, fv = _bilinear_corner(x, y, inv_res)
    mask = (1 << shift) - 1
    li = i0 & mask
    lj = j0 & mask
    tx = (i0 >> shift) - tile_x0
    ty = (j0 >> shift) - tile_y0
    if li < mask and lj < mask and 0 <= tx < tables.shape[2] and 0 <= ty < tables.shape[1]:
        # all four cells in one tile (the common case): one table lookup
        t = tables[p, ty, tx]
        if t < 0:
            return 0.5, 0.0, 0.0
        v00 = _squash(squash, pool[t, lj, li])
        v10 = _squash(squash, pool[t, lj, li + 1])
        v01 = _squash(squash, pool[t, lj + 1, li])
        v11 = _squash(squash, pool[t, lj + 1, li + 1])
    else:
        v00 = _squash(squash, cell_value(pool, tables, p, tile_x0, tile_y0, shift, i0, j0))
        v10 = _squash(squash, cell_value(pool, tables, p, tile_x0, tile_y0, shift, i0 + 1, j0))
        v01 = _squash(squash, cell_value(pool, tables, p, tile_x0, tile_y0, shift, i0, j0 + 1))
        v11 = _squash(squash, cell_value(pool, tables, p, tile_x0, tile_y0, shift, i0 + 1, j0 + 1))
    m, dmdu, dmdv = _bilinear(v00, v10, v01, v11, fu, fv)
    return m, dmdu * inv_res, dmdv * inv_res


@nb.njit(cache=True, nogil=True)
def _cell_value(pool, tables, p, tile_x0, tile_y0, shift, cx, cy):
    """:func:`slam_engine.frontend.grid.cell_value` as a called (not inlined) function: for the rare point whose
    four cells span tiles."""
    return cell_value(pool, tables, p, tile_x0, tile_y0, shift, cx, cy)


@nb.njit(cache=True, nogil=True, inline="always")
def _evaluate(squash, pool, tables, p, tile_x0, tile_y0, shift, inv_res, points_v, stride, x, y, theta, H, g):
    """Sum of squared residuals (1 - M) at pose (x, y, theta), filling the Gauss-Newton system
    H (3, 3) and g (3,) (for the step that lowers the residuals). Returns (E, sum M, n)."""
    c = math.cos(theta)
    s = math.sin(theta)
    h00 = h01 = h02 = h11 = h12 = h22 = 0.0
    g0 = g1 = g2 = 0.0
    e = 0.0
    m_sum = 0.0
    n = 0
    mask = (1 << shift) - 1
    n_ty = tables.shape[1]
    n_tx = tables.shape[2]
    for i in range(0, points_v.shape[0], stride):
        px = points_v[i, 0]
        py = points_v[i, 1]
        wx = x + c * px - s * py
        wy = y + s * px + c * py
        # :func:`_sample`'s cell lookups written out here: an inlined helper taking arrays costs numba
        # reference counting (atomic increments) at every point (1.4x slower)
        i0, j0, fu, fv = _bilinear_corner(wx, wy, inv_res)
        li = i0 & mask
        lj = j0 & mask
        tx = (i0 >> shift) - tile_x0
        ty = (j0 >> shift) - tile_y0
        if li < mask and lj < mask and 0 <= tx < n_tx and 0 <= ty < n_ty:  # all four cells in one tile
            t = tables[p, ty, tx]
            if t < 0:
                v00 = v10 = v01 = v11 = 0.5
            else:
                v00 = squash[pool[t, lj, li] + SQUASH_OFFSET]
                v10 = squash[pool[t, lj, li + 1] + SQUASH_OFFSET]
                v01 = squash[pool[t, lj + 1, li] + SQUASH_OFFSET]
                v11 = squash[pool[t, lj + 1, li + 1] + SQUASH_OFFSET]
        else:
            v00 = squash[_cell_value(pool, tables, p, tile_x0, tile_y0, shift, i0, j0) + SQUASH_OFFSET]
            v10 = squash[_cell_value(pool, tables, p, tile_x0, tile_y0, shift, i0 + 1, j0) + SQUASH_OFFSET]
            v01 = squash[_cell_value(pool, tables, p, tile_x0, tile_y0, shift, i0, j0 + 1) + SQUASH_OFFSET]
            v11 = squash[_cell_value(pool, tables, p, tile_x0, tile_y0, shift, i0 + 1, j0 + 1) + SQUASH_OFFSET]
        m, dmdu, dmdv = _bilinear(v00, v10, v01, v11, fu, fv)
        mx = dmdu * inv_res
        my = dmdv * inv_res
        r = 1.0 - m
        jt = mx * (-s * px - c * py) + my * (c * px - s * py)
        h00 += mx * mx
        h01 += mx * my
        h02 += mx * jt
        h11 += my * my
        h12 += my * jt
        h22 += jt * jt
        g0 += mx * r
        g1 += my * r
        g2 += jt * r
        e += r * r
        m_sum += m
        n += 1
    H[0, 0] = h00
    H[0, 1] = H[1, 0] = h01
    H[0, 2] = H[2, 0] = h02
    H[1, 1] = h11
    H[1, 2] = H[2, 1] = h12
    H[2, 2] = h22
    g[0] = g0
    g[1] = g1
    g[2] = g2
    return e, m_sum, n


@nb.njit(cache=True, nogil=True)
def _fit_level(squash, pool, tables, p, tile_x0, tile_y0, shift, inv_res, points_v, stride, pose, prior_pose, prior_w,
               iterations, H):
    """Damped Gauss-Newton (Levenberg-Marquardt) on one level; updates ``pose`` in place. Returns
    :func:`_evaluate`'s (E, sum M, n) at the final pose (without the prior), and leaves its ``H`` in
    ``H`` (3, 3)."""
    g = np.zeros(3)
    H2 = np.zeros((3, 3))
    g2 = np.zeros(3)
    A = np.zeros((3, 3))
    e, m_sum, n = _evaluate(squash, pool, tables, p, tile_x0, tile_y0, shift, inv_res, points_v, stride,
                            pose[0], pose[1], pose[2], H, g)
    e_data = e
    d0 = pose[0] - prior_pose[0]
    d1 = pose[1] - prior_pose[1]
    d2 = pose[2] - prior_pose[2]
    e += prior_w[0] * d0 * d0 + prior_w[1] * d1 * d1 + prior_w[2] * d2 * d2
    lam = 1e-3
    b = np.zeros(3)
    cand = np.zeros(3)
    for _ in range(iterations):
        for a in range(3):
            for c in range(3):
                A[a, c] = H[a, c]
            A[a, a] += lam * (H[a, a] + 1e-9) + prior_w[a]
        b[0] = g[0] - prior_w[0] * (pose[0] - prior_pose[0])
        b[1] = g[1] - prior_w[1] * (pose[1] - prior_pose[1])
        b[2] = g[2] - prior_w[2] * (pose[2] - prior_pose[2])
        step = np.linalg.solve(A, b)
        for a in range(3):
            cand[a] = pose[a] + step[a]
        e2_data, m_sum2, n2 = _evaluate(squash, pool, tables, p, tile_x0, tile_y0, shift, inv_res, points_v, stride,
                                        cand[0], cand[1], cand[2], H2, g2)
        d0 = cand[0] - prior_pose[0]
        d1 = cand[1] - prior_pose[1]
        d2 = cand[2] - prior_pose[2]
        e2 = e2_data + prior_w[0] * d0 * d0 + prior_w[1] * d1 * d1 + prior_w[2] * d2 * d2
        if e2 < e:
            for a in range(3):
                pose[a] = cand[a]
                g[a] = g2[a]
                for c in range(3):
                    H[a, c] = H2[a, c]
            small = abs(step[0]) + abs(step[1]) < 2e-3 / inv_res and abs(step[2]) < 5e-5
            e = e2
            e_data, m_sum, n = e2_data, m_sum2, n2
            lam *= 0.3
            if small:
                break
        else:
            lam *= 8.0
            if lam > 1e4:
                break
    return e_data, m_sum, n


@nb.njit(cache=True, nogil=True, parallel=True)
def match_particles(squash, levels0, levels1, levels2, levels3, tables, tile_x0, tile_y0, particles, init_poses,
                    points_v, resolution_m, coarsest_level, iterations, strides, prior_w, presearch, out_poses, out_e,
                    out_mean, out_H):
    """Fit the scan ``points_v`` (B, 2, vehicle frame [m]) onto the map of each particle index in
    ``particles`` starting from ``init_poses`` (P, 3). Writes the fitted poses, the level-0
    sum of squared residuals over all points, the mean map value at the end points and the
    Gauss-Newton matrix ``J^T J`` (3, 3) of the residuals at the fitted pose.
    ``presearch`` = (half width xy [m], half width theta [rad], gain, info_x, info_y, info_theta):
    with a positive half width, a correlative search on the coarsest level picks the start of the
    fit first (:func:`_presearch`).
    Particles run in parallel threads (maps are only read; row k of the outputs is written by one
    thread), with the same results as a serial loop."""
    for k in nb.prange(particles.shape[0]):
        _match_one(squash, levels0, levels1, levels2, levels3, tables, tile_x0, tile_y0, particles[k], init_poses[k],
                   points_v, resolution_m, coarsest_level, iterations, strides, prior_w, presearch, out_poses, out_e,
                   out_mean, out_H, k)


@nb.njit(cache=True, nogil=True)
def _presearch(squash, pool, tables, p, tile_x0, tile_y0, shift, inv_res, points_v, stride, init_pose, presearch,
               step_xy, step_theta, start):
    """Correlative search around ``init_pose`` on one (coarse) level: every heading step_theta apart
    and every translation step_xy apart within the half widths, scored by the log-likelihood
    ``-gain * mean (1 - M)^2`` plus the motion prior ``-0.5 d^T diag(info) d``; writes the best into
    ``start``."""
    win_xy, win_th, gain = presearch[0], presearch[1], presearch[2]
    nx = int(win_xy / step_xy)
    na = int(win_th / step_theta)
    n_pts = (points_v.shape[0] + stride - 1) // stride
    rx = np.empty(n_pts)
    ry = np.empty(n_pts)
    best = -1e300
    start[0] = init_pose[0]
    start[1] = init_pose[1]
    start[2] = init_pose[2]
    for a in range(-na, na + 1):
        dth = a * step_theta
        th = init_pose[2] + dth
        c = math.cos(th)
        s = math.sin(th)
        for i in range(n_pts):
            px = points_v[i * stride, 0]
            py = points_v[i * stride, 1]
            rx[i] = c * px - s * py
            ry[i] = s * px + c * py
        for ix in range(-nx, nx + 1):
            dx = ix * step_xy
            for iy in range(-nx, nx + 1):
                dy = iy * step_xy
                x = init_pose[0] + dx
                y = init_pose[1] + dy
                e = 0.0
                for i in range(n_pts):
                    m, _, _ = _sample(squash, pool, tables, p, tile_x0, tile_y0, shift, inv_res, x + rx[i], y + ry[i])
                    e += (1.0 - m) * (1.0 - m)
                value = -gain * e / n_pts - 0.5 * (presearch[3] * dx * dx + presearch[4] * dy * dy
                                                   + presearch[5] * dth * dth)
                if value > best:
                    best = value
                    start[0] = x
                    start[1] = y
                    start[2] = th


@nb.njit(cache=True, nogil=True)
def _match_one(squash, levels0, levels1, levels2, levels3, tables, tile_x0, tile_y0, p, init_pose, points_v,
               resolution_m, coarsest_level, iterations, strides, prior_w, presearch, out_poses, out_e, out_mean,
               out_H, k):
    """:func:`match_particles` for particle p from ``init_pose``; writes row k of the outputs."""
    H = np.zeros((3, 3))
    g = np.zeros(3)
    pose = init_pose.copy()
    prior = init_pose.copy()
    if presearch[0] > 0.0 or presearch[1] > 0.0:
        shift = TILE_SHIFT - coarsest_level
        cell = resolution_m * (1 << coarsest_level)
        pool = levels3 if coarsest_level == 3 else (levels2 if coarsest_level == 2 else
                                                    (levels1 if coarsest_level == 1 else levels0))
        stride = max(strides[coarsest_level], points_v.shape[0] // 60)
        _presearch(squash, pool, tables, p, tile_x0, tile_y0, shift, 1.0 / cell, points_v, stride, init_pose,
                   presearch, 0.5 * cell, PRESEARCH_STEP_RAD, pose)
    for level in range(coarsest_level, -1, -1):
        shift = TILE_SHIFT - level
        inv_res = 1.0 / (resolution_m * (1 << level))
        if level == 3:
            pool = levels3
        elif level == 2:
            pool = levels2
        elif level == 1:
            pool = levels1
        else:
            pool = levels0
        e, m_sum, n = _fit_level(squash, pool, tables, p, tile_x0, tile_y0, shift, inv_res, points_v, strides[level],
                                 pose, prior, prior_w, iterations[level], H)
    if strides[0] != 1:  # level 0's fit read every strides[0]-th point: the outputs hold all of them
        e, m_sum, n = _evaluate(squash, levels0, tables, p, tile_x0, tile_y0, TILE_SHIFT, 1.0 / resolution_m, points_v,
                                1, pose[0], pose[1], pose[2], H, g)
    out_poses[k, 0] = pose[0]
    out_poses[k, 1] = pose[1]
    out_poses[k, 2] = pose[2]
    out_e[k] = e
    out_mean[k] = m_sum / max(n, 1)
    for a in range(3):
        for b in range(3):
            out_H[k, a, b] = H[a, b]


@nb.njit(cache=True, nogil=True)
def score_particles(squash, levels0, tables, tile_x0, tile_y0, particles, poses, points_v, resolution_m, out_e,
                    out_mean):
    """Level-0 sum of squared residuals and mean map value of the scan at given poses (no fit)."""
    H = np.zeros((3, 3))
    g = np.zeros(3)
    for k in range(particles.shape[0]):
        e, m_sum, n = _evaluate(squash, levels0, tables, particles[k], tile_x0, tile_y0, TILE_SHIFT, 1.0 / resolution_m,
                                points_v, 1, poses[k, 0], poses[k, 1], poses[k, 2], H, g)
        out_e[k] = e
        out_mean[k] = m_sum / max(n, 1)


@dataclass
class ParticleMatches:
    """Scan matches of P particles: ``poses`` (P, 3), level-0 ``sq_residual`` (P,) = sum (1 - M)^2,
    ``mean_score`` (P,) mean M, ``accepted`` (P,), ``jtj`` (P, 3, 3) Gauss-Newton matrix of the
    residuals at the fitted pose (the information of the match up to the likelihood's gain)."""

    poses: np.ndarray
    sq_residual: np.ndarray
    mean_score: np.ndarray
    accepted: np.ndarray
    jtj: np.ndarray


class ScanMatcher:
    """Coarse-to-fine scan matching of one scan against each particle's own map.

    ``search_xy_m`` / ``search_theta_rad``: how far the fit may move a pose from its odometry
    prediction (farther = rejected) and the scale of the weak prior; ``min_score``: lowest mean map
    value M at the end points for an accepted match; ``beam_skip``: use every n-th end point on the
    finest level (coarser levels thin out further)."""

    def __init__(self, search_xy_m: float, search_theta_rad: float, min_score: float, beam_skip: int = 1,
                 coarsest_level: int = N_LEVELS - 1, iterations: tuple[int, ...] = (15, 3, 3, 3),
                 prior_weight: float = 1.0):
        self.search_xy_m = float(search_xy_m)
        self.search_theta_rad = float(search_theta_rad)
        self.min_score = float(min_score)
        self.coarsest_level = int(coarsest_level)
        self.iterations = np.asarray(iterations, np.int64)
        # coarse levels only need every other point: their cells are large
        self.strides = np.array([beam_skip * (2 if k >= 2 else 1) for k in range(N_LEVELS)], np.int64)
        self.prior_weight = float(prior_weight)
        self.prior_w = self._prior_weights(self.search_xy_m, self.search_theta_rad)

    def _prior_weights(self, window_xy_m: float, window_theta_rad: float) -> np.ndarray:
        """Weights of the weak prior that holds the fit near its start where the scan leaves a
        direction unconstrained: one window width costs ``prior_weight``."""
        sxy = max(window_xy_m, 1e-3)
        sth = max(window_theta_rad, 1e-3)
        return np.array([self.prior_weight / sxy**2, self.prior_weight / sxy**2, self.prior_weight / sth**2])

    def fit(self, grids: ParticleGrids, particles: np.ndarray, predicted: np.ndarray, points_v: np.ndarray,
            window_xy_m: float | None = None, window_theta_rad: float | None = None,
            presearch: np.ndarray | None = None) -> ParticleMatches:
        """Fit ``points_v`` (B, 2) for each particle index in ``particles`` from ``predicted`` (P, 3),
        accepting moves up to ``window_xy_m`` / ``window_theta_rad`` (default: the matcher's own).
        ``presearch`` = (half width xy [m], half width theta [rad], gain, info_x, info_y, info_theta)
        turns on a coarse correlative search over that window before the fit (None: off; a zero half
        width leaves that dimension to the fit).

        Where a match is not accepted the pose is the prediction and the residual and score are
        those of the prediction."""
        win_xy = self.search_xy_m if window_xy_m is None else float(window_xy_m)
        win_th = self.search_theta_rad if window_theta_rad is None else float(window_theta_rad)
        prior_w = self.prior_w if window_xy_m is None else self._prior_weights(win_xy, win_th)
        pre = np.zeros(6) if presearch is None else np.ascontiguousarray(presearch, np.float64)
        particles = np.ascontiguousarray(particles, np.int64)
        predicted = np.ascontiguousarray(predicted, np.float64)
        points_v = np.ascontiguousarray(points_v, np.float64)
        n = particles.shape[0]
        poses = np.empty((n, 3))
        e = np.empty(n)
        mean = np.empty(n)
        jtj = np.empty((n, 3, 3))
        lv = grids.levels
        match_particles(SQUASH, lv[0], lv[1], lv[2], lv[3], grids.tables, grids.tile_x0, grids.tile_y0, particles,
                        predicted, points_v, grids.resolution_m, self.coarsest_level, self.iterations, self.strides,
                        prior_w, pre, poses, e, mean, jtj)
        moved = poses - predicted
        moved[:, 2] = (moved[:, 2] + np.pi) % (2 * np.pi) - np.pi
        accepted = ((mean >= self.min_score) & (np.hypot(moved[:, 0], moved[:, 1]) <= win_xy)
                    & (np.abs(moved[:, 2]) <= win_th))
        if not accepted.all():
            rejected = ~accepted
            e[rejected], mean[rejected] = self.score(grids, particles[rejected], predicted[rejected], points_v)
            poses[rejected] = predicted[rejected]
        poses[:, 2] = (poses[:, 2] + np.pi) % (2 * np.pi) - np.pi
        return ParticleMatches(poses, e, mean, accepted, jtj)

    def score(self, grids: ParticleGrids, particles: np.ndarray, poses: np.ndarray, points_v: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
        """Level-0 sum of squared residuals and mean map value of ``points_v`` at ``poses`` (no fit)."""
        particles = np.ascontiguousarray(particles, np.int64)
        e = np.empty(len(particles))
        mean = np.empty(len(particles))
        score_particles(SQUASH, grids.levels[0], grids.tables, grids.tile_x0, grids.tile_y0, particles,
                        np.ascontiguousarray(poses, np.float64), np.ascontiguousarray(points_v, np.float64),
                        grids.resolution_m, e, mean)
        return e, mean

    def match(self, grids: ParticleGrids, particles: np.ndarray, predicted: np.ndarray,
              points_v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`fit` within the matcher's own window, as ``(poses, sum_sq_residual, mean_score,
        accepted)``."""
        m = self.fit(grids, particles, predicted, points_v)
        return m.poses, m.sq_residual, m.mean_score, m.accepted
