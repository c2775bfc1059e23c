"""How usable a map is as it comes out: free space outside the mapped structure (the *halo*).

A free cell belongs to the halo when it lies more than ``margin_m`` beyond the outermost occupied
cells of the rows (or columns) within ``margin_m`` of its own, along that row (column): free space
that no wall bounds, e.g. the rays that beams without a return clear around a building, which a
planner (Nav2) would happily use. (Computed as: occupied cells dilated by a square of half width
``margin_m``; a free cell beyond the first or last dilated cell of its row or of its column is in
the halo. Looking at the neighbouring rows too keeps a room behind a window gap of up to
``2 * margin_m`` in the outer wall inside.) Free and occupied are the thresholds of ``map.pgm``
(:mod:`slam_engine.products.rendering`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from slam_engine.model.result import OccupancyGrid
from slam_engine.products.rendering import FREE_THRESHOLD, OCCUPIED_THRESHOLD

DEFAULT_HALO_MARGIN_M = 1.0


@dataclass(frozen=True)
class HaloStats:
    """``free_cells``: free cells of the map; ``halo_cells``: those in the halo; ``halo_share`` =
    halo / free (0 for a map without free cells); ``margin_m`` the margin used [m]."""

    free_cells: int
    halo_cells: int
    halo_share: float
    margin_m: float

    def as_dict(self) -> dict:
        return {"free_cells": self.free_cells, "halo_cells": self.halo_cells, "halo_share": self.halo_share,
                "margin_m": self.margin_m}


def _outside_along_rows(occupied: np.ndarray) -> np.ndarray:
    """(H, W) bool: cells left of the first or right of the last occupied cell of their row; every
    cell of a row without an occupied cell."""
    h, w = occupied.shape
    any_row = np.asarray(occupied.any(axis=1))
    first = np.where(any_row, occupied.argmax(axis=1), w)
    last = np.where(any_row, w - 1 - occupied[:, ::-1].argmax(axis=1), -1)
    col = np.arange(w)[None, :]
    return (col < first[:, None]) | (col > last[:, None]) | ~any_row[:, None]


def halo_mask(grid: OccupancyGrid, margin_m: float = DEFAULT_HALO_MARGIN_M) -> np.ndarray:
    """(H, W) bool: the free cells of ``grid`` that lie in the halo (module docstring)."""
    if margin_m < 0:
        raise ValueError(f"margin_m must be >= 0, got {margin_m}")
    probability, known = grid.probability(), grid.known()
    occupied = known & (probability > OCCUPIED_THRESHOLD)
    free = known & (probability < FREE_THRESHOLD)
    margin_cells = int(np.floor(margin_m / grid.resolution_m + 1e-9))
    if margin_cells > 0:
        occupied = ndimage.binary_dilation(occupied, np.ones((3, 3), bool), iterations=margin_cells)
    outside = _outside_along_rows(occupied) | _outside_along_rows(occupied.T).T
    return free & outside


def halo_stats(grid: OccupancyGrid, margin_m: float = DEFAULT_HALO_MARGIN_M) -> HaloStats:
    """Free cells, halo cells and their share for ``grid`` (module docstring)."""
    known = grid.known()
    free_cells = int(np.count_nonzero(known & (grid.probability() < FREE_THRESHOLD)))
    halo_cells = int(np.count_nonzero(halo_mask(grid, margin_m)))
    return HaloStats(free_cells=free_cells, halo_cells=halo_cells,
                     halo_share=halo_cells / free_cells if free_cells else 0.0, margin_m=float(margin_m))
