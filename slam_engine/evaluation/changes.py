"""How well a change map found the changes a simulated world was given (cell level).

The truth is walls taken away and put up (``changes.json`` beside a simulated log, world frame),
drawn into the change map's cells. A detected cell is right when a true change of its kind lies within
``tolerance_cells`` of it (precision); a true change counts as found when a detected cell of its kind
lies within ``tolerance_cells`` (recall), over the true cells the drives could show: a wall taken
away where the saved map held it and the new drive looked through it, a wall put up where the new
drive's beams ended on it.
"""

from __future__ import annotations

import numpy as np

from slam_engine.model.poses import place_points
from slam_engine.multisession.changes import ChangeMap


def wall_cells(walls: np.ndarray, T_map_from_world: np.ndarray, changes: ChangeMap) -> np.ndarray:
    """(H, W) bool: the cells of ``changes`` that walls (S, 4) [x0, y0, x1, y1] m (world frame) cross."""
    rows, cols = changes.added.shape
    out = np.zeros((rows, cols), bool)
    step = changes.resolution_m / 4
    for x0, y0, x1, y1 in np.asarray(walls, np.float64).reshape(-1, 4):
        n = max(2, int(np.ceil(np.hypot(x1 - x0, y1 - y0) / step)) + 1)
        points = np.column_stack([np.linspace(x0, x1, n), np.linspace(y0, y1, n)])
        cells = np.floor((place_points(T_map_from_world, points) - changes.origin_m) / changes.resolution_m)
        ix, iy = cells[:, 0].astype(np.int64), cells[:, 1].astype(np.int64)
        inside = (ix >= 0) & (iy >= 0) & (ix < cols) & (iy < rows)
        out[iy[inside], ix[inside]] = True
    return out


def change_accuracy(changes: ChangeMap, removed_walls: np.ndarray, added_walls: np.ndarray,
                    T_map_from_world: np.ndarray, tolerance_cells: int = 1) -> dict:
    """Cell-level precision and recall of ``changes`` against the true walls removed and added (world
    frame; ``T_map_from_world`` (3,) places them in the change map's frame), for each kind and both."""
    from scipy import ndimage

    near = np.ones((2 * tolerance_cells + 1,) * 2, bool)

    def grow(mask: np.ndarray) -> np.ndarray:
        return ndimage.binary_dilation(mask, near) if tolerance_cells else mask

    truth = {"removed": wall_cells(removed_walls, T_map_from_world, changes),
             "added": wall_cells(added_walls, T_map_from_world, changes)}
    shown = {"removed": truth["removed"] & grow(changes.saved_occupied) & (changes.passes > 0),
             "added": truth["added"] & grow(changes.hits > 0)}
    found = {"removed": changes.removed, "added": changes.added}
    out: dict = {"tolerance_cells": tolerance_cells, "resolution_m": changes.resolution_m}
    right_total = detected_total = caught_total = shown_total = 0
    for kind in ("added", "removed"):
        right = int((found[kind] & grow(truth[kind])).sum())
        caught = int((shown[kind] & grow(found[kind])).sum())
        detected, true_cells = int(found[kind].sum()), int(shown[kind].sum())
        out[kind] = {"detected_cells": detected, "true_cells": true_cells,
                     "precision": right / detected if detected else None,
                     "recall": caught / true_cells if true_cells else None}
        right_total, detected_total = right_total + right, detected_total + detected
        caught_total, shown_total = caught_total + caught, shown_total + true_cells
    out["precision"] = right_total / detected_total if detected_total else None
    out["recall"] = caught_total / shown_total if shown_total else None
    return out
