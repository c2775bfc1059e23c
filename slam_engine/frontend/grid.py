"""Log-odds occupancy maps for every particle, stored as shared copy-on-write tiles.

Layout: the map frame is cut into square tiles of ``TILE`` x ``TILE`` cells. Tiles live in one
pool (``levels[0]`` is ``(capacity, TILE, TILE)`` int16 log-odds in units of ``LOG_ODDS_UNIT``,
so 0.9 is stored as 90: half the memory traffic of float32); each particle has a tile table
(``tables[p, ty, tx]`` -> pool index, -1 = never observed) over a tile window that grows with the
drive (``tile_x0``, ``tile_y0`` = global tile index of table column/row 0). A pool tile carries a
reference count: resampling copies only tables, and a particle writes into a tile only after
making it private (copy when shared). Unchanged parts of the map are shared by every particle.

Coarser copies of each tile (``levels[k]``, cells ``2**k`` times larger, max of the finer
log-odds) give the scan matcher a smooth, wide basin of attraction.

Local maps: every tile position carries the travel [m] at which a scan last touched it
(``touched_at``, on the ``clock_m`` the filter advances). :meth:`ParticleGrids.forget_stale` takes the
tiles no scan touched for a while out of every particle's table, so that a particle matches only
what it mapped recently: back in a place mapped long ago, the scan meets a fresh map instead of
the old pass where the drift put it (the loops are the back end's to close). The forgotten tiles
of the leading particle are kept in ``archive`` (level 0 only), which previews still show.

Cell ``(gx, gy)`` (global indices) covers ``[gx * res, (gx + 1) * res)`` in the map frame, so the
map frame's origin is a cell corner; tiles and levels follow the same rule.
"""

from __future__ import annotations

import math
import os

import numba as nb
import numpy as np

from slam_engine.frontend.tile_layout import (  # noqa: F401 (TILE_SHIFT: the kernels import it from here)
    N_LEVELS,
    POOL_DTYPE,
    POOL_GROWTH_DIVISOR,
    TILE,
    TILE_SHIFT,
)
from slam_engine.model.result import OccupancyGrid

# Thread pool of the parallel per-particle loops (raycast, scan_matcher): OpenMP first. numba would
# try TBB first, and Open3D's bundled TBB is too old for numba: a warning, then OpenMP anyway.
if not {"NUMBA_THREADING_LAYER", "NUMBA_THREADING_LAYER_PRIORITY"} & os.environ.keys():
    # numba.config creates its settings through globals() at import, invisible to its type information
    nb.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]  # type: ignore[attr-defined]

TABLE_MARGIN_TILES = 4
LOG_ODDS_UNIT = 0.01  # stored log-odds are integers in these units


def _grown(array: np.ndarray, length: int) -> np.ndarray:
    """``array`` with its first axis grown to ``length``, new entries 0. An array that owns its
    memory is resized in place (realloc: a large pool is moved by remapping its pages, never copied,
    so growing needs no second pool); the pool arrays are only ever passed to kernels for one call,
    never kept (a view held across a growth would point to freed memory). Otherwise: copied."""
    if array.flags.owndata and array.base is None:
        array.resize((length,) + array.shape[1:], refcheck=False)
        return array
    grown = np.zeros((length,) + array.shape[1:], array.dtype)
    grown[: array.shape[0]] = array
    return grown


def quantize_log_odds(value: float) -> int:
    """A log-odds value (increment or clamp) in stored units (nonzero values stay nonzero)."""
    q = int(round(value / LOG_ODDS_UNIT))
    if q == 0 and value != 0:
        q = 1 if value > 0 else -1
    return q


@nb.njit(cache=True, nogil=True, inline="always")
def cell_value(pool, tables, p, tile_x0, tile_y0, shift, cx, cy):
    """Stored log-odds (units of ``LOG_ODDS_UNIT``) of global cell (cx, cy) of particle p's map at
    the level whose tiles are ``1 << shift`` cells wide; 0 (unknown) outside the observed tiles."""
    tx = (cx >> shift) - tile_x0
    ty = (cy >> shift) - tile_y0
    if tx < 0 or ty < 0 or ty >= tables.shape[1] or tx >= tables.shape[2]:
        return 0
    t = tables[p, ty, tx]
    if t < 0:
        return 0
    mask = (1 << shift) - 1
    return int(pool[t, cy & mask, cx & mask])


@nb.njit(cache=True, nogil=True)
def _privatize(levels0, levels1, levels2, levels3, tables, refcount, free_stack, n_free, touched, n_touched):
    """Make tiles ``touched[:n_touched] = (p, ty, tx)`` private to their particle: a missing tile
    becomes a fresh unknown tile, a shared one a copy. Returns the new number of free tiles."""
    for k in range(n_touched):
        p = touched[k, 0]
        ty = touched[k, 1]
        tx = touched[k, 2]
        t = tables[p, ty, tx]
        if t >= 0 and refcount[t] == 1:
            continue
        n_free -= 1
        new = free_stack[n_free]
        if t < 0:
            levels0[new, :, :] = 0
            levels1[new, :, :] = 0
            levels2[new, :, :] = 0
            levels3[new, :, :] = 0
        else:
            levels0[new, :, :] = levels0[t]
            levels1[new, :, :] = levels1[t]
            levels2[new, :, :] = levels2[t]
            levels3[new, :, :] = levels3[t]
            refcount[t] -= 1
            if refcount[t] == 0:  # cannot happen with refcount > 1 above, kept for safety
                free_stack[n_free] = t
                n_free += 1
        refcount[new] = 1
        tables[p, ty, tx] = new
    return n_free


@nb.njit(cache=True, nogil=True)
def _rebuild_coarse(levels0, levels1, levels2, levels3, tables, touched, n_touched):
    """Recompute the coarse levels (max of 2x2 finer cells) of the touched tiles."""
    for k in range(n_touched):
        t = tables[touched[k, 0], touched[k, 1], touched[k, 2]]
        if t < 0:
            continue
        for src, dst in ((levels0, levels1), (levels1, levels2), (levels2, levels3)):
            n = dst.shape[1]
            for i in range(n):
                for j in range(n):
                    a = src[t, 2 * i, 2 * j]
                    b = src[t, 2 * i, 2 * j + 1]
                    c = src[t, 2 * i + 1, 2 * j]
                    d = src[t, 2 * i + 1, 2 * j + 1]
                    m = a if a > b else b
                    m2 = c if c > d else d
                    dst[t, i, j] = m if m > m2 else m2


@nb.njit(cache=True, nogil=True)
def _tiles_to_grid(levels0, table, r0, r1, c0, c1, archive_index, archive_tiles, pool, scale):
    """The float32 log-odds grid of the tiles of ``table`` (one particle's tile table) in rows
    ``r0:r1`` and columns ``c0:c1``, each cell its stored value (plus that of the archived tile
    ``archive_tiles[archive_index[r, c]]`` where the index is not -1) divided by ``scale``; 0 where
    no tile is. With ``pool`` > 1 the grid pooled as :func:`~slam_engine.frontend.map_pooling.pool_known_max`
    pools it (each block the largest of its known, non-zero cells), without the full-resolution
    grid: the largest stored value of a block, divided once (division by a positive scale keeps the
    order, rounding included, and only a stored 0 gives 0)."""
    tile = levels0.shape[1]
    h = (r1 - r0) * tile
    w = (c1 - c0) * tile
    pooled = pool > 1
    unknown = np.iinfo(np.int32).min
    # pooled: the largest stored value of each block; else the cells themselves, written as they come
    best = np.full(((h + pool - 1) // pool, (w + pool - 1) // pool) if pooled else (1, 1), unknown, np.int32)
    full = np.zeros((1, 1) if pooled else (h, w), np.float32)
    column_of = np.empty(tile, np.int64)  # the output column of each cell column of a tile
    for c in range(c0, c1):
        for j in range(tile):
            column_of[j] = ((c - c0) * tile + j) // pool
        for r in range(r0, r1):
            t = table[r, c]
            a = archive_index[r, c]
            if t < 0 and a < 0:
                continue
            for i in range(tile):
                out_row = ((r - r0) * tile + i) // pool
                for j in range(tile):
                    stored = np.int32(0)
                    if t >= 0:
                        stored += np.int32(levels0[t, i, j])
                    if a >= 0:
                        stored += np.int32(archive_tiles[a, i, j])
                    if stored == 0:
                        continue
                    if not pooled:
                        full[out_row, column_of[j]] = np.float32(stored) / scale
                    elif stored > best[out_row, column_of[j]]:
                        best[out_row, column_of[j]] = stored
    if not pooled:
        return full
    out = np.zeros(best.shape, np.float32)
    for i in range(best.shape[0]):
        for j in range(best.shape[1]):
            if best[i, j] != unknown:
                out[i, j] = np.float32(best[i, j]) / scale
    return out


class ParticleGrids:
    """Occupancy maps of up to ``n_particles`` particles sharing copy-on-write tiles (as many as
    :meth:`resample` last gave, ``n_particles`` at first).

    ``resolution_m``: level-0 cell size [m]. Maps grow as the drive reaches new tiles; no bounds
    are set by hand."""

    def __init__(self, n_particles: int, resolution_m: float, initial_capacity: int = 256):
        self.n_particles = int(n_particles)
        self.resolution_m = float(resolution_m)
        self.levels = [np.zeros((initial_capacity, TILE >> k, TILE >> k), POOL_DTYPE) for k in range(N_LEVELS)]
        self.refcount = np.zeros(initial_capacity, np.int32)
        self.free_stack = np.arange(initial_capacity - 1, -1, -1, dtype=np.int32)
        self.n_free = initial_capacity
        self.tables = np.full((self.n_particles, 1, 1), -1, np.int32)
        self.tile_x0 = 0
        self.tile_y0 = 0
        self._touched = np.zeros((1024, 3), np.int32)
        self._mark = np.zeros((self.n_particles, 1, 1), np.uint8)
        self.clock_m = 0.0  # travel so far [m], advanced by the filter
        self.touched_at = np.full((1, 1), -np.inf)  # clock_m when a scan last touched each tile position
        # forgotten level-0 tiles of the leading particle: previews show them. Stacked (``archive_tiles``,
        # slot by global (tile y, tile x) in ``archive_slots``), so that a map is drawn without copying them
        self.archive_tiles = np.zeros((0, TILE, TILE), POOL_DTYPE)
        self.archive_slots: dict[tuple[int, int], int] = {}

    # --- geometry -------------------------------------------------------------------------
    @property
    def capacity(self) -> int:
        return self.levels[0].shape[0]

    @property
    def tile_size_m(self) -> float:
        return TILE * self.resolution_m

    @property
    def archive(self) -> dict[tuple[int, int], np.ndarray]:
        """The forgotten level-0 tiles of the leading particle by global (tile y, tile x) (views)."""
        return {key: self.archive_tiles[slot] for key, slot in self.archive_slots.items()}

    def world_to_cell(self, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Global level-0 cell indices of map-frame points [m]."""
        return (np.floor(np.asarray(x_m) / self.resolution_m).astype(np.int64),
                np.floor(np.asarray(y_m) / self.resolution_m).astype(np.int64))

    def cell_to_world(self, gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map-frame centres [m] of global level-0 cells."""
        return ((np.asarray(gx) + 0.5) * self.resolution_m, (np.asarray(gy) + 0.5) * self.resolution_m)

    def ensure_extent(self, x_min_m: float, y_min_m: float, x_max_m: float, y_max_m: float) -> None:
        """Grow the tile tables so that the box [m] lies inside them (with a margin)."""
        size = self.tile_size_m
        tx_lo, ty_lo = int(np.floor(x_min_m / size)), int(np.floor(y_min_m / size))
        tx_hi, ty_hi = int(np.floor(x_max_m / size)), int(np.floor(y_max_m / size))
        _, h, w = self.tables.shape
        if tx_lo >= self.tile_x0 and ty_lo >= self.tile_y0 and tx_hi < self.tile_x0 + w and ty_hi < self.tile_y0 + h:
            return
        new_x0 = min(self.tile_x0, tx_lo - TABLE_MARGIN_TILES)
        new_y0 = min(self.tile_y0, ty_lo - TABLE_MARGIN_TILES)
        new_w = max(self.tile_x0 + w, tx_hi + 1 + TABLE_MARGIN_TILES) - new_x0
        new_h = max(self.tile_y0 + h, ty_hi + 1 + TABLE_MARGIN_TILES) - new_y0
        tables = np.full((self.tables.shape[0], new_h, new_w), -1, np.int32)
        ox, oy = self.tile_x0 - new_x0, self.tile_y0 - new_y0
        tables[:, oy:oy + h, ox:ox + w] = self.tables
        touched_at = np.full((new_h, new_w), -np.inf)
        touched_at[oy:oy + h, ox:ox + w] = self.touched_at
        self.tables, self.touched_at, self.tile_x0, self.tile_y0 = tables, touched_at, new_x0, new_y0
        self._mark = np.zeros((self.n_particles, new_h, new_w), np.uint8)

    def ensure_free(self, n_tiles: int) -> None:
        """Grow the pool so that ``n_tiles`` tiles can be allocated: by 1/32 at least, in place
        where possible (the allocator moves the pages instead of copying them: no second pool while
        growing), so the pool stays within about 1/32 of the most tiles the drive ever needed (the
        new tiles are zeroed, so they are resident from the growth on)."""
        if self.n_free >= n_tiles:
            return
        old = self.capacity
        new = max(old + old // POOL_GROWTH_DIVISOR, old + n_tiles - self.n_free + 64)
        self.levels = [_grown(lv, new) for lv in self.levels]
        self.refcount = _grown(self.refcount, new)
        stack = np.empty(new, np.int32)
        stack[: self.n_free] = self.free_stack[: self.n_free]
        stack[self.n_free: self.n_free + new - old] = np.arange(new - 1, old - 1, -1, dtype=np.int32)
        self.free_stack = stack
        self.n_free += new - old

    # --- copy on write --------------------------------------------------------------------
    def touched_buffer(self, n: int) -> np.ndarray:
        """A scratch (n, 3) int32 buffer for touched (particle, ty, tx) entries."""
        if self._touched.shape[0] < n:
            self._touched = np.zeros((max(n, 2 * self._touched.shape[0]), 3), np.int32)
        return self._touched

    def privatize(self, touched: np.ndarray, n_touched: int) -> None:
        """Make the touched tiles writable by their particle (fresh or copied)."""
        entries = touched[:n_touched]
        t = self.tables[entries[:, 0], entries[:, 1], entries[:, 2]]
        needed = int(np.count_nonzero((t < 0) | (self.refcount[np.maximum(t, 0)] > 1)))
        self.ensure_free(needed)
        lv = self.levels
        self.n_free = int(_privatize(lv[0], lv[1], lv[2], lv[3], self.tables, self.refcount, self.free_stack,
                                     self.n_free, touched, n_touched))

    def rebuild_coarse(self, touched: np.ndarray, n_touched: int) -> None:
        lv = self.levels
        _rebuild_coarse(lv[0], lv[1], lv[2], lv[3], self.tables, touched, n_touched)

    def resample(self, ancestors: np.ndarray) -> None:
        """Particle i takes the map of particle ``ancestors[i]`` (tables copied, tiles shared); there
        may be fewer ancestors than particles, or more, up to ``n_particles``."""
        ancestors = np.asarray(ancestors)
        if len(ancestors) > self.n_particles:
            raise ValueError(f"resample: {len(ancestors)} particles, at most {self.n_particles}")
        self.tables = self.tables[ancestors]
        self._recount()

    def _recount(self) -> None:
        """Reference counts and free tiles from the tables."""
        used = self.tables[self.tables >= 0]
        self.refcount = np.bincount(used, minlength=self.capacity).astype(np.int32)
        free = np.flatnonzero(self.refcount == 0).astype(np.int32)
        self.free_stack = np.empty(self.capacity, np.int32)
        self.free_stack[: len(free)] = free[::-1]
        self.n_free = len(free)

    def forget_stale(self, cutoff_m: float, keep: int, log_odds_min: int, log_odds_max: int) -> int:
        """Take out of every particle's table the tiles no scan touched since travel ``cutoff_m``;
        particle ``keep``'s are added (log-odds, clamped to the stored ``log_odds_min``/``max``) to
        :attr:`archive`. Returns the number of tile positions forgotten."""
        # a position holds tiles only once a scan touched it (forgetting resets it to -inf): the stamps
        # alone say which, without reading every particle's table
        stale = np.isfinite(self.touched_at) & (self.touched_at < cutoff_m)
        if not stale.any():
            return 0
        for ty, tx in zip(*np.nonzero(stale), strict=True):
            t = self.tables[keep, ty, tx]
            if t < 0:
                continue
            key = (int(self.tile_y0 + ty), int(self.tile_x0 + tx))
            slot = self.archive_slots.get(key)
            tile = self.levels[0][t]
            if slot is None:
                slot = self._archive_slot(key)
                self.archive_tiles[slot] = tile
            else:
                kept = self.archive_tiles[slot]
                kept[...] = np.clip(kept.astype(np.int32) + tile, log_odds_min, log_odds_max)
        self.tables[:, stale] = -1
        self.touched_at[stale] = -np.inf
        self._recount()
        return int(stale.sum())

    def _archive_slot(self, key: tuple[int, int]) -> int:
        """A new archive slot for tile position ``key`` (the stack grows by a quarter when full)."""
        slot = len(self.archive_slots)
        if slot == len(self.archive_tiles):  # copied, not resized in place: views of it may be held
            grown = np.zeros((slot + slot // 4 + 16, TILE, TILE), POOL_DTYPE)
            grown[:slot] = self.archive_tiles
            self.archive_tiles = grown
        self.archive_slots[key] = slot
        return slot

    def keep_only(self, particle: int | None) -> None:
        """Drop every map but particle ``particle``'s (None: every map): the other tables are emptied
        and the pool shrinks to that particle's tiles (what reading its map needs once the drive is
        over)."""
        table = self.tables[0] if particle is None else self.tables[particle]
        observed = np.flatnonzero(table.ravel() >= 0) if particle is not None else np.zeros(0, np.int64)
        tiles = table.ravel()[observed]
        self.levels = [np.ascontiguousarray(lv[tiles]) for lv in self.levels]
        kept = np.full(table.shape, -1, np.int32)
        kept.ravel()[observed] = np.arange(len(tiles), dtype=np.int32)
        self.tables = np.full(self.tables.shape, -1, np.int32)
        if particle is not None:
            self.tables[particle] = kept
        self.refcount = np.ones(len(tiles), np.int32)
        self.free_stack = np.zeros(0, np.int32)
        self.n_free = 0
        if particle is None:
            self.archive_tiles = np.zeros((0, TILE, TILE), POOL_DTYPE)
            self.archive_slots = {}

    # --- reporting ------------------------------------------------------------------------
    def tiles_in_use(self) -> int:
        return self.capacity - self.n_free

    def memory_bytes(self) -> int:
        """Bytes held by the pool, the tables and the scratch buffers."""
        return int(sum(lv.nbytes for lv in self.levels) + self.refcount.nbytes + self.free_stack.nbytes
                   + self.tables.nbytes + self._mark.nbytes + self._touched.nbytes + self.touched_at.nbytes
                   + self.archive_tiles.nbytes)

    def _archived_positions(self) -> tuple[np.ndarray, np.ndarray]:
        """Rows and columns (of the tables) of the archived tiles, in slot order."""
        keys = np.array(list(self.archive_slots), np.int64).reshape(-1, 2)
        return keys[:, 0] - self.tile_y0, keys[:, 1] - self.tile_x0

    def _observed_tiles(self, particle: int, archived: tuple[np.ndarray, np.ndarray] | None = None
                        ) -> tuple[np.ndarray, np.ndarray]:
        """Rows and columns (of the tables) of the tiles of ``particle``'s map and of the archive
        (``archived``: :meth:`_archived_positions`, when the caller has them already)."""
        rows, cols = np.nonzero(self.tables[particle] >= 0)
        archived_rows, archived_cols = self._archived_positions() if archived is None else archived
        return np.concatenate([rows, archived_rows]), np.concatenate([cols, archived_cols])

    def observed_shape(self, particle: int) -> tuple[int, int]:
        """(rows, cols) of :meth:`occupancy_grid` of ``particle`` at full resolution (without making it)."""
        rows, cols = self._observed_tiles(particle)
        if len(rows) == 0:
            return 1, 1
        return int(rows.max() - rows.min() + 1) * TILE, int(cols.max() - cols.min() + 1) * TILE

    def occupancy_grid_within(self, particle: int, max_side_cells: int) -> OccupancyGrid:
        """:meth:`occupancy_grid` pooled by the smallest factor that brings it to at most
        ``max_side_cells`` cells a side (the factor :meth:`MapSnapshot.reduced` applies to the full map)."""
        side = max(self.observed_shape(particle))
        return self.occupancy_grid(particle, pool=max(1, math.ceil(side / max_side_cells)))

    def occupancy_grid(self, particle: int, pool: int = 1) -> OccupancyGrid:
        """Particle ``particle``'s level-0 map (with the archive's forgotten tiles added) as a dense
        float32 grid cropped to its observed tiles; with ``pool`` > 1, that grid pooled by ``pool``
        (:meth:`OccupancyGrid.pooled`), built from the tiles (:func:`_tiles_to_grid`) so that the
        full-resolution grid never exists."""
        archived = self._archived_positions()
        rows, cols = self._observed_tiles(particle, archived)
        if len(rows) == 0:
            return OccupancyGrid(np.zeros((1, 1), np.float32), self.resolution_m, 0.0, 0.0)
        r0, r1, c0, c1 = int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1
        origin_x = float((self.tile_x0 + c0) * self.tile_size_m)
        origin_y = float((self.tile_y0 + r0) * self.tile_size_m)
        pool = max(1, int(pool))
        archive_index = np.full(self.tables.shape[1:], -1, np.int32)  # slots are numbered in insertion order
        archive_index[archived] = np.arange(len(self.archive_slots), dtype=np.int32)
        # the same float32 values as converting the whole int16 grid, then dividing
        scale = np.float32(1.0 / LOG_ODDS_UNIT)
        grid = _tiles_to_grid(self.levels[0], self.tables[particle], r0, r1, c0, c1, archive_index,
                              self.archive_tiles, pool, scale)
        return OccupancyGrid(grid, self.resolution_m * pool, origin_x, origin_y)
