"""Insert one scan into every particle's occupancy map (numba).

Each beam runs from the LiDAR's cell to its end cell (Bresenham): the cells it crosses get
``log_odds_miss``, its end cell ``log_odds_hit`` when the beam returned. Beams without a return
(or longer than the grid's ``max_range_m``) clear free space along their whole length and add no
hit. Values are clamped to ``[log_odds_min, log_odds_max]``; increments and clamps are rounded to the
pool's integer units (``grid.LOG_ODDS_UNIT`` = 0.01).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from slam_engine.grid import TILE, TILE_SHIFT, ParticleGrids, quantize_log_odds


@nb.njit(cache=True, nogil=True, inline="always")
def _mark(mark, out, count, p, tx, ty):
    if ty < 0 or tx < 0 or ty >= mark.shape[1] or tx >= mark.shape[2]:
        return count
    if mark[p, ty, tx] == 0:
        mark[p, ty, tx] = 1
        if count < out.shape[0]:
            out[count, 0] = p
            out[count, 1] = ty
            out[count, 2] = tx
        count += 1
    return count


@nb.njit(cache=True, nogil=True, inline="always")
def _mark_segment(mark, out, count, p, x0, y0, x1, y1, tile_x0, tile_y0):
    """Mark every tile the segment (x0, y0)-(x1, y1) [tile units] crosses (grid traversal)."""
    tx = int(math.floor(x0))
    ty = int(math.floor(y0))
    tx_end = int(math.floor(x1))
    ty_end = int(math.floor(y1))
    count = _mark(mark, out, count, p, tx - tile_x0, ty - tile_y0)
    dx = x1 - x0
    dy = y1 - y0
    step_x = 1 if dx > 0 else -1
    step_y = 1 if dy > 0 else -1
    t_delta_x = abs(1.0 / dx) if dx != 0 else 1e30
    t_delta_y = abs(1.0 / dy) if dy != 0 else 1e30
    t_max_x = ((tx + 1 - x0) if dx > 0 else (x0 - tx)) * t_delta_x if dx != 0 else 1e30
    t_max_y = ((ty + 1 - y0) if dy > 0 else (y0 - ty)) * t_delta_y if dy != 0 else 1e30
    guard = abs(tx_end - tx) + abs(ty_end - ty) + 2
    while (tx != tx_end or ty != ty_end) and guard > 0:
        guard -= 1
        if abs(t_max_x - t_max_y) < 1e-9:  # through a corner: mark both neighbours
            count = _mark(mark, out, count, p, tx + step_x - tile_x0, ty - tile_y0)
            count = _mark(mark, out, count, p, tx - tile_x0, ty + step_y - tile_y0)
            tx += step_x
            ty += step_y
            t_max_x += t_delta_x
            t_max_y += t_delta_y
        elif t_max_x < t_max_y:
            tx += step_x
            t_max_x += t_delta_x
        else:
            ty += step_y
            t_max_y += t_delta_y
        count = _mark(mark, out, count, p, tx - tile_x0, ty - tile_y0)
    return _mark(mark, out, count, p, tx_end - tile_x0, ty_end - tile_y0)


# Bresenham cells between two cell centres lie on the tiles of the line between them, but a beam
# that starts clearing part-way (``free_from_m``) runs from a cell up to about a cell off that line:
# the tiles of the lines shifted by this many cells across the beam cover every cell it writes.
_SPREAD_CELLS = 1.0


@nb.njit(cache=True, nogil=True, parallel=True)
def collect_touched_tiles(particles, poses, origin_v, ends_v, resolution_m, tile_x0, tile_y0, mark, out):
    """Mark (in ``mark``, list in ``out``) every tile a beam of each particle ``particles[k]`` (at
    ``poses[k]``) writes: the tiles crossed by the segment between the cell centres of the LiDAR and
    the beam's end and by that segment shifted ``_SPREAD_CELLS`` either way along its minor axis.
    Returns the number of distinct (particle, tile) pairs, listed particle by particle in the order
    found (as a serial loop would). Particles run in parallel threads, each listing into its own
    ``len(out) // len(poses)`` rows of ``out``; when a particle needs more, the return value exceeds
    ``len(out)`` (rows enough for every particle to list as many as the busiest): the caller grows
    ``out``, clears ``mark`` and calls again."""
    n_poses = poses.shape[0]
    per = out.shape[0] // n_poses
    counts = np.zeros(n_poses, np.int64)
    for k in nb.prange(n_poses):
        counts[k] = _collect_particle(particles[k], poses[k], origin_v, ends_v, resolution_m, tile_x0, tile_y0, mark,
                                      out[k * per:(k + 1) * per])
    busiest = counts.max()
    if busiest > per:
        return max(busiest * n_poses, out.shape[0] + 1)
    total = 0
    for k in range(n_poses):  # compact: row total <= k * per, so rows are copied forward only
        for i in range(counts[k]):
            for j in range(3):
                out[total, j] = out[k * per + i, j]
            total += 1
    return total


@nb.njit(cache=True, nogil=True)
def _collect_particle(p, pose, origin_v, ends_v, resolution_m, tile_x0, tile_y0, mark, out):
    """:func:`collect_touched_tiles` for particle p at ``pose`` (3,), listing into ``out``."""
    count = 0
    tile = float(TILE)
    spread = _SPREAD_CELLS / tile
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    ox = pose[0] + c * origin_v[0] - s * origin_v[1]
    oy = pose[1] + s * origin_v[0] + c * origin_v[1]
    x0 = (math.floor(ox / resolution_m) + 0.5) / tile
    y0 = (math.floor(oy / resolution_m) + 0.5) / tile
    for b in range(ends_v.shape[0]):
        ex = pose[0] + c * ends_v[b, 0] - s * ends_v[b, 1]
        ey = pose[1] + s * ends_v[b, 0] + c * ends_v[b, 1]
        x1 = (math.floor(ex / resolution_m) + 0.5) / tile
        y1 = (math.floor(ey / resolution_m) + 0.5) / tile
        count = _mark_segment(mark, out, count, p, x0, y0, x1, y1, tile_x0, tile_y0)
        if abs(x1 - x0) >= abs(y1 - y0):
            count = _mark_segment(mark, out, count, p, x0, y0 - spread, x1, y1 - spread, tile_x0, tile_y0)
            count = _mark_segment(mark, out, count, p, x0, y0 + spread, x1, y1 + spread, tile_x0, tile_y0)
        else:
            count = _mark_segment(mark, out, count, p, x0 - spread, y0, x1 - spread, y1, tile_x0, tile_y0)
            count = _mark_segment(mark, out, count, p, x0 + spread, y0, x1 + spread, y1, tile_x0, tile_y0)
    return count


@nb.njit(cache=True, nogil=True)
def clear_marks(mark, out, n):
    for k in range(n):
        mark[out[k, 0], out[k, 1], out[k, 2]] = 0


@nb.njit(cache=True, nogil=True, inline="always")
def _max4(a, b, c, d):
    m = a if a > b else b
    m2 = c if c > d else d
    return m if m > m2 else m2


@nb.njit(cache=True, nogil=True, inline="always")
def _add(levels0, levels1, levels2, levels3, t, iy, ix, delta, lo, hi):
    """Add ``delta`` to cell (iy, ix) of pool tile t (clamped) and keep the coarse maxima current."""
    old = levels0[t, iy, ix]
    v = old + delta
    if v < lo:
        v = lo
    elif v > hi:
        v = hi
    if v == old:
        return
    levels0[t, iy, ix] = v
    i = iy >> 1
    j = ix >> 1
    m = _max4(levels0[t, 2 * i, 2 * j], levels0[t, 2 * i, 2 * j + 1], levels0[t, 2 * i + 1, 2 * j],
              levels0[t, 2 * i + 1, 2 * j + 1])
    if m == levels1[t, i, j]:
        return
    levels1[t, i, j] = m
    i >>= 1
    j >>= 1
    m = _max4(levels1[t, 2 * i, 2 * j], levels1[t, 2 * i, 2 * j + 1], levels1[t, 2 * i + 1, 2 * j],
              levels1[t, 2 * i + 1, 2 * j + 1])
    if m == levels2[t, i, j]:
        return
    levels2[t, i, j] = m
    i >>= 1
    j >>= 1
    levels3[t, i, j] = _max4(levels2[t, 2 * i, 2 * j], levels2[t, 2 * i, 2 * j + 1], levels2[t, 2 * i + 1, 2 * j],
                             levels2[t, 2 * i + 1, 2 * j + 1])


@nb.njit(cache=True, nogil=True, inline="always")
def _tile_of(tables, refcount, p, tile_x0, tile_y0, gx, gy):
    """Pool index of the (private) tile holding global cell (gx, gy), or -1."""
    tx = (gx >> TILE_SHIFT) - tile_x0
    ty = (gy >> TILE_SHIFT) - tile_y0
    if tx < 0 or ty < 0 or ty >= tables.shape[1] or tx >= tables.shape[2]:
        return -1
    t = tables[p, ty, tx]
    if t < 0 or refcount[t] != 1:
        return -1
    return t


@nb.njit(cache=True, nogil=True, parallel=True)
def integrate_rays(levels0, levels1, levels2, levels3, tables, refcount, tile_x0, tile_y0, particles, poses,
                   origin_v, ends_v, is_hit, free_from_m, resolution_m, log_odds_hit, log_odds_miss, log_odds_min,
                   log_odds_max):
    """Apply every beam to the map of each particle ``particles[k]`` at ``poses[k]``: misses along
    the beams first, then the hits, so a wall cell crossed by a grazing beam of the same scan still gains
    its hit. Beam b clears cells from ``free_from_m[b]`` on (near the LiDAR its neighbours already cover
    every cell).

    Particles run in parallel threads: ``particles`` must be distinct and a particle writes only its
    private tiles (reference count 1, made so serially by :meth:`ParticleGrids.privatize` beforehand),
    so no two threads touch one tile and the maps equal those of a serial loop bit for bit."""
    for k in nb.prange(poses.shape[0]):
        _integrate_particle(levels0, levels1, levels2, levels3, tables, refcount, tile_x0, tile_y0, particles[k],
                            poses[k], origin_v, ends_v, is_hit, free_from_m, resolution_m, log_odds_hit,
                            log_odds_miss, log_odds_min, log_odds_max)


@nb.njit(cache=True, nogil=True)
def _integrate_particle(levels0, levels1, levels2, levels3, tables, refcount, tile_x0, tile_y0, p, pose, origin_v,
                        ends_v, is_hit, free_from_m, resolution_m, log_odds_hit, log_odds_miss, log_odds_min,
                        log_odds_max):
    """:func:`integrate_rays` for particle p at ``pose`` (3,)."""
    mask = TILE - 1
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    ox = pose[0] + c * origin_v[0] - s * origin_v[1]
    oy = pose[1] + s * origin_v[0] + c * origin_v[1]
    for b in range(ends_v.shape[0]):
        ex = pose[0] + c * ends_v[b, 0] - s * ends_v[b, 1]
        ey = pose[1] + s * ends_v[b, 0] + c * ends_v[b, 1]
        length = math.hypot(ex - ox, ey - oy)
        if free_from_m[b] >= length:
            if is_hit[b]:
                continue
            frac = 1.0
        else:
            frac = free_from_m[b] / length if length > 0 else 0.0
        gx0 = int(math.floor((ox + frac * (ex - ox)) / resolution_m))
        gy0 = int(math.floor((oy + frac * (ey - oy)) / resolution_m))
        gx1 = int(math.floor(ex / resolution_m))
        gy1 = int(math.floor(ey / resolution_m))
        # Bresenham from (gx0, gy0) to (gx1, gy1); the end cell is free too for no-return beams
        dx = abs(gx1 - gx0)
        dy = -abs(gy1 - gy0)
        sx = 1 if gx0 < gx1 else -1
        sy = 1 if gy0 < gy1 else -1
        err = dx + dy
        x = gx0
        y = gy0
        key_x = x >> TILE_SHIFT
        key_y = y >> TILE_SHIFT
        t = _tile_of(tables, refcount, p, tile_x0, tile_y0, x, y)
        while True:
            last = x == gx1 and y == gy1
            if last and is_hit[b]:
                break
            if (x >> TILE_SHIFT) != key_x or (y >> TILE_SHIFT) != key_y:
                key_x = x >> TILE_SHIFT
                key_y = y >> TILE_SHIFT
                t = _tile_of(tables, refcount, p, tile_x0, tile_y0, x, y)
            if t >= 0:
                _add(levels0, levels1, levels2, levels3, t, y & mask, x & mask, log_odds_miss, log_odds_min,
                     log_odds_max)
            if last:
                break
            e2 = 2 * err
            if e2 >= dy:
                err += dy
                x += sx
            if e2 <= dx:
                err += dx
                y += sy
    for b in range(ends_v.shape[0]):
        if not is_hit[b]:
            continue
        ex = pose[0] + c * ends_v[b, 0] - s * ends_v[b, 1]
        ey = pose[1] + s * ends_v[b, 0] + c * ends_v[b, 1]
        x = int(math.floor(ex / resolution_m))
        y = int(math.floor(ey / resolution_m))
        t = _tile_of(tables, refcount, p, tile_x0, tile_y0, x, y)
        if t >= 0:
            _add(levels0, levels1, levels2, levels3, t, y & mask, x & mask, log_odds_hit, log_odds_min,
                 log_odds_max)


def insert_scan(
    grids: ParticleGrids,
    poses: np.ndarray,
    origin_v: np.ndarray,
    ends_v: np.ndarray,
    is_hit: np.ndarray,
    log_odds_hit: float,
    log_odds_miss: float,
    log_odds_min: float,
    log_odds_max: float,
    free_from_m: np.ndarray | None = None,
    particles: np.ndarray | None = None,
) -> int:
    """Insert one scan into the maps of ``particles`` (indices; None = 0..P-1).

    ``poses`` (P, 3) vehicle poses of those particles in the map frame; ``origin_v`` (2,) the
    LiDAR's position in the vehicle frame [m]; ``ends_v`` (B, 2) beam end points in the vehicle
    frame [m]; ``is_hit`` (B,) False for free-space-only beams; ``free_from_m`` (B,) where each beam
    starts clearing [m] (:func:`slam_engine.lidar_points.free_space_start_m`; None: from the LiDAR).
    Particles are inserted in parallel (numba threads); ``particles`` must be distinct.
    Returns the number of (particle, tile) pairs written."""
    poses = np.ascontiguousarray(poses, dtype=np.float64)
    origin_v = np.ascontiguousarray(origin_v, dtype=np.float64)
    ends_v = np.ascontiguousarray(ends_v, dtype=np.float64)
    is_hit = np.ascontiguousarray(is_hit, dtype=np.bool_)
    if ends_v.shape[0] == 0:
        return 0
    particles = np.arange(poses.shape[0]) if particles is None else particles
    particles = np.ascontiguousarray(particles, dtype=np.int64)
    if len(np.unique(particles)) != len(particles):  # parallel insertion needs one writer per map
        raise ValueError(f"insert_scan: particle indices must be distinct, got {particles.tolist()}")
    # grow the tile tables to cover every beam of every particle
    reach = float(np.hypot(*np.vstack([ends_v, origin_v[None, :]]).T).max())
    grids.ensure_extent(poses[:, 0].min() - reach, poses[:, 1].min() - reach,
                        poses[:, 0].max() + reach, poses[:, 1].max() + reach)
    buffer = grids.touched_buffer(poses.shape[0] * 64)
    n = collect_touched_tiles(particles, poses, origin_v, ends_v, grids.resolution_m, grids.tile_x0, grids.tile_y0,
                              grids._mark, buffer)
    if n > buffer.shape[0]:
        grids._mark[:] = 0
        buffer = grids.touched_buffer(n)
        n = collect_touched_tiles(particles, poses, origin_v, ends_v, grids.resolution_m, grids.tile_x0, grids.tile_y0,
                                  grids._mark, buffer)
    grids.privatize(buffer, n)
    free_from = np.zeros(len(ends_v)) if free_from_m is None else np.ascontiguousarray(free_from_m, np.float64)
    lv = grids.levels
    integrate_rays(lv[0], lv[1], lv[2], lv[3], grids.tables, grids.refcount, grids.tile_x0, grids.tile_y0, particles,
                   poses, origin_v, ends_v, is_hit, free_from, grids.resolution_m,
                   quantize_log_odds(log_odds_hit), quantize_log_odds(log_odds_miss), quantize_log_odds(log_odds_min),
                   quantize_log_odds(log_odds_max))
    clear_marks(grids._mark, buffer, n)
    return n
