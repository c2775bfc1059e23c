"""The halo measure: free space outside the mapped structure."""

from __future__ import annotations

import numpy as np
import pytest

from slam_engine.evaluation.halo import halo_mask, halo_stats
from slam_engine.model.result import OccupancyGrid

FREE, OCCUPIED = -2.0, 2.0  # log-odds: p = 0.12 (free) and 0.88 (occupied)


def building(window: bool = False) -> np.ndarray:
    """30 x 30 m at 0.1 m: a 10 m square room (walls at cells 100 and 200), free inside, a ray of free
    cells from the east wall out to cell 279 along row 150; ``window``: a 0.9 m gap in the east wall."""
    log_odds = np.zeros((300, 300))
    log_odds[101:200, 101:200] = FREE
    for k in (100, 200):
        log_odds[100:201, k] = OCCUPIED
        log_odds[k, 100:201] = OCCUPIED
    log_odds[150, 201:280] = FREE
    if window:
        log_odds[140:149, 200] = FREE
    return log_odds


def test_free_cells_beyond_the_margin_outside_the_walls_are_the_halo() -> None:
    grid = OccupancyGrid(building(), 0.1, -5.0, -5.0)
    stats = halo_stats(grid, margin_m=1.0)
    # the ray's cells more than 10 cells beyond the wall (x index 211..279) are the halo
    assert stats.halo_cells == 69
    assert stats.free_cells == 99 * 99 + 79
    assert stats.halo_share == pytest.approx(69 / (99 * 99 + 79))
    assert np.array_equal(np.nonzero(halo_mask(grid, 1.0))[1], np.arange(211, 280))
    assert halo_stats(grid, margin_m=0.0).halo_cells == 79  # every cell beyond the wall itself


def test_a_window_in_the_outer_wall_keeps_the_room_inside() -> None:
    grid = OccupancyGrid(building(window=True), 0.1, -5.0, -5.0)
    assert halo_stats(grid, margin_m=1.0).halo_cells == 69  # the room behind the 0.9 m gap is no halo


def test_maps_without_free_cells_or_walls() -> None:
    empty = OccupancyGrid(np.zeros((10, 10)), 0.1, 0.0, 0.0)
    assert halo_stats(empty).as_dict() == {"free_cells": 0, "halo_cells": 0, "halo_share": 0.0, "margin_m": 1.0}
    open_field = OccupancyGrid(np.full((10, 10), FREE), 0.1, 0.0, 0.0)
    assert halo_stats(open_field).halo_share == 1.0  # nothing bounds it
    with pytest.raises(ValueError, match="margin_m"):
        halo_mask(open_field, -1.0)
