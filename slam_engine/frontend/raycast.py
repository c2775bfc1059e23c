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

from slam_engine.frontend.grid import TILE, TILE_SHIFT, ParticleGrids, quantize_log_odds


@nb.njit(cache=True, nogil=True, inline="always")
def _mark_band(mark, out, count, p, x0, y0, x1, y1, spread, transpose, tile_x0, tile_y0):
    """Mark every tile that the band of half width ``spread`` around the segment (x0, y0)-(x1, y1)
    [tile units] overlaps, the band measured along y, for ``|x1 - x0| >= |y1 - y0|``. The segment is
    walked one tile column at a time: in a column the band spans ``[min y - spread, max y + spread]``.
    ``transpose``: the coordinates are (y, x), so the tiles marked are (column = y, row = x)."""
    if x1 < x0:
        x0, y0, x1, y1 = x1, y1, x0, y0
    slope = (y1 - y0) / (x1 - x0) if x1 > x0 else 0.0
    for col in range(int(math.floor(x0)), int(math.floor(x1)) + 1):
        ya = y0 + (max(x0, col) - x0) * slope
        yb = y0 + (min(x1, col + 1.0) - x0) * slope
        lo = int(math.floor(min(ya, yb) - spread))
        hi = int(math.floor(max(ya, yb) + spread))
        for row in range(lo, hi + 1):
            if transpose:
                tx, ty = row - tile_x0, col - tile_y0
            else:
                tx, ty = col - tile_x0, row - tile_y0
            # marked and listed here, not in a helper: an inlined helper taking arrays costs numba
            # reference counting at every call
            if 0 <= ty < mark.shape[1] and 0 <= tx < mark.shape[2] and mark[p, ty, tx] == 0:
                mark[p, ty, tx] = 1
                if count < out.shape[0]:
                    out[count, 0] = p
                    out[count, 1] = ty
                    out[count, 2] = tx
                count += 1
    return count


# Bresenham cells between two cell centres lie on the tiles of the line between them, but a beam
# that starts clearing part-way (``free_from_m``) runs from a cell up to about a cell off that line:
# the tiles of the band this many cells either side of the line (across the beam) cover every cell
# it writes.
_SPREAD_CELLS = 1.0


@nb.njit(cache=True, nogil=True)
def collect_touched_tiles(particles, poses, origin_v, ends_v, resolution_m, tile_x0, tile_y0, mark, out):
    """Mark (in ``mark``, list in ``out``) every tile a beam of each particle ``particles[k]`` (at
    ``poses[k]``) writes: the tiles overlapped by the band ``_SPREAD_CELLS`` wide either side (along
    its minor axis) of the segment between the cell centres of the LiDAR and the beam's end.
    Returns the number of distinct (particle, tile) pairs, listed particle by particle in the order
    found; when it exceeds ``len(out)`` (the rows past it are not listed) the caller grows ``out``,
    clears ``mark`` and calls again. Serial: in threads it took longer (a fraction of a millisecond
    a scan, less than waking them)."""
    count = 0
    for k in range(poses.shape[0]):
        count = _collect_particle(particles[k], poses[k], origin_v, ends_v, resolution_m, tile_x0, tile_y0, mark,
                                  out, count)
    return count


@nb.njit(cache=True, nogil=True)
def _collect_particle(p, pose, origin_v, ends_v, resolution_m, tile_x0, tile_y0, mark, out, count):
    """:func:`collect_touched_tiles` for particle p at ``pose`` (3,), listing into ``out`` from row
    ``count`` on; returns the new count."""
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
        if abs(x1 - x0) >= abs(y1 - y0):
            count = _mark_band(mark, out, count, p, x0, y0, x1, y1, spread, False, tile_x0, tile_y0)
        else:
            count = _mark_band(mark, out, count, p, y0, x0, y1, x1, spread, True, tile_x0, tile_y0)
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
def _raise(levels0, levels1, levels2, levels3, t, iy, ix, delta, hi):
    """Add ``delta`` > 0 to cell (iy, ix) of pool tile t, clamped at ``hi``; the coarse maxima above
    the cell rise with it."""
    v = levels0[t, iy, ix] + delta
    if v > hi:
        v = hi
    if v <= levels0[t, iy, ix]:
        return
    levels0[t, iy, ix] = v
    i = iy >> 1
    j = ix >> 1
    if v <= levels1[t, i, j]:
        return
    levels1[t, i, j] = v
    i >>= 1
    j >>= 1
    if v <= levels2[t, i, j]:
        return
    levels2[t, i, j] = v
    i >>= 1
    j >>= 1
    if v > levels3[t, i, j]:
        levels3[t, i, j] = v


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
    n_ty = tables.shape[1]
    n_tx = tables.shape[2]
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
        # Bresenham from (gx0, gy0) to (gx1, gy1): max(|dx|, |dy|) steps; the end cell is free too
        # for no-return beams
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
        n_cells = max(dx, -dy) + (0 if is_hit[b] else 1)
        # the hot loop, written out: an inlined helper taking arrays costs numba reference counting
        # (atomic increments) at every call, which made this loop 1.7x slower
        for _ in range(n_cells):
            if (x >> TILE_SHIFT) != key_x or (y >> TILE_SHIFT) != key_y:
                key_x = x >> TILE_SHIFT
                key_y = y >> TILE_SHIFT
                tx = key_x - tile_x0
                ty = key_y - tile_y0
                t = -1
                if 0 <= tx < n_tx and 0 <= ty < n_ty:
                    t = tables[p, ty, tx]
                    if t >= 0 and refcount[t] != 1:
                        t = -1
            if t >= 0:
                # add log_odds_miss to the cell, clamped at log_odds_min; a coarse maximum the cell held
                # is recomputed (max of its 2x2 finer cells), level by level while it changes
                iy = y & mask
                ix = x & mask
                old = levels0[t, iy, ix]
                v = max(old + log_odds_miss, log_odds_min)
                if v < old:
                    levels0[t, iy, ix] = v
                    i = iy >> 1
                    j = ix >> 1
                    if old >= levels1[t, i, j]:
                        m = _max4(levels0[t, 2 * i, 2 * j], levels0[t, 2 * i, 2 * j + 1], levels0[t, 2 * i + 1, 2 * j],
                                  levels0[t, 2 * i + 1, 2 * j + 1])
                        if m != old:
                            levels1[t, i, j] = m
                            i >>= 1
                            j >>= 1
                            if old >= levels2[t, i, j]:
                                m = _max4(levels1[t, 2 * i, 2 * j], levels1[t, 2 * i, 2 * j + 1],
                                          levels1[t, 2 * i + 1, 2 * j], levels1[t, 2 * i + 1, 2 * j + 1])
                                if m != old:
                                    levels2[t, i, j] = m
                                    i >>= 1
                                    j >>= 1
                                    if old >= levels3[t, i, j]:
                                        levels3[t, i, j] = _max4(levels2[t, 2 * i, 2 * j], levels2[t, 2 * i, 2 * j + 1],
                                                                 levels2[t, 2 * i + 1, 2 * j],
                                                                 levels2[t, 2 * i + 1, 2 * j + 1])
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
            _raise(levels0, levels1, levels2, levels3, t, y & mask, x & mask, log_odds_hit, log_odds_max)


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
    starts clearing [m] (:func:`slam_engine.frontend.lidar_points.free_space_start_m`; None: from the LiDAR).
    Particles are inserted in parallel (numba threads); ``particles`` must be distinct.
    Returns the number of (particle, tile) pairs written."""
    poses = np.ascontiguousarray(poses, dtype=np.float64)
    origin_v = np.ascontiguousarray(origin_v, dtype=np.float64)
    ends_v = np.ascontiguousarray(ends_v, dtype=np.float64)
    is_hit = np.ascontiguousarray(is_hit, dtype=np.bool_)
    if not (log_odds_miss < 0 < log_odds_hit and log_odds_min < 0 < log_odds_max):
        raise ValueError("insert_scan: needs log_odds_miss < 0 < log_odds_hit and log_odds_min < 0 < log_odds_max")
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
    grids.touched_at[buffer[:n, 1], buffer[:n, 2]] = grids.clock_m
    free_from = np.zeros(len(ends_v)) if free_from_m is None else np.ascontiguousarray(free_from_m, np.float64)
    lv = grids.levels
    log_odds = (quantize_log_odds(log_odds_hit), quantize_log_odds(log_odds_miss), quantize_log_odds(log_odds_min),
                quantize_log_odds(log_odds_max))
    if len(particles) == 1:  # one map (the product map's): no threads to wake
        _integrate_particle(lv[0], lv[1], lv[2], lv[3], grids.tables, grids.refcount, grids.tile_x0, grids.tile_y0,
                            particles[0], poses[0], origin_v, ends_v, is_hit, free_from, grids.resolution_m, *log_odds)
    else:
        integrate_rays(lv[0], lv[1], lv[2], lv[3], grids.tables, grids.refcount, grids.tile_x0, grids.tile_y0,
                       particles, poses, origin_v, ends_v, is_hit, free_from, grids.resolution_m, *log_odds)
    clear_marks(grids._mark, buffer, n)
    return n
