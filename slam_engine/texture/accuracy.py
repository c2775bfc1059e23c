"""How well a texture map reproduces a known floor (simulated logs): colour error and placement.

The run's map frame is placed in the floor's (ground truth's) frame by the best rigid 2-D alignment
of the SLAM trajectory onto the ground truth (poses matched by time, as for the ATE). Each scored
cell's true colour is the mean of the floor over the cell (``samples`` x ``samples`` points).

- *colour error*: mean (and median) absolute difference per channel, 0-255, between the texture and
  the true cell colours (grayscale textures against the floor's luminance);
- *placement*: the shift of the texture, in whole cells (at most ``max_shift_cells`` each way),
  that fits the floor best (least mean colour error); (0, 0) means placed within one cell.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from slam_engine.evaluation.metrics import align_rigid_2d, match_times
from slam_engine.model.result import TextureMap, Trajectory

FloorRgb = Callable[[np.ndarray, np.ndarray], np.ndarray]
_LUMINANCE = np.array([0.299, 0.587, 0.114])


@dataclass(frozen=True)
class TextureAccuracy:
    """``observed_cells``: cells the texture has; ``scored_cells``: those compared (an even sample
    when there are many); colour errors in 0-255 per channel; ``placement_offset_cells`` (dx, dy):
    the texture's best-fitting shift in the map frame [cells], ``placement_offset_m`` its length [m];
    ``colour_error_at_offset`` the mean colour error after that shift."""

    observed_cells: int
    scored_cells: int
    colour_error_mean: float
    colour_error_median: float
    placement_offset_cells: tuple[int, int]
    placement_offset_m: float
    colour_error_at_offset: float

    def as_dict(self) -> dict:
        return {"observed_cells": self.observed_cells, "scored_cells": self.scored_cells,
                "colour_error_mean": self.colour_error_mean, "colour_error_median": self.colour_error_median,
                "placement_offset_cells": list(self.placement_offset_cells),
                "placement_offset_m": self.placement_offset_m, "colour_error_at_offset": self.colour_error_at_offset}


def map_to_truth_frame(trajectory: Trajectory, ground_truth: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """(R (2, 2), t (2,)) taking map-frame points into the ground truth's frame: the best rigid
    alignment of the trajectory's positions onto the ground truth's (matched by time). ValueError
    when fewer than two poses match."""
    index = match_times(ground_truth.t_s, trajectory.t_s)
    matched = index >= 0
    if int(matched.sum()) < 2:
        raise ValueError("fewer than two trajectory poses have a ground-truth pose at their time")
    return align_rigid_2d(np.asarray(trajectory.poses)[matched, :2], np.asarray(ground_truth.poses)[index[matched], :2])


def texture_accuracy(texture: TextureMap, floor_rgb: FloorRgb, rotation: np.ndarray, translation: np.ndarray,
                     max_cells: int = 20000, max_shift_cells: int = 2, samples: int = 4) -> TextureAccuracy:
    """Colour error and placement of ``texture`` against ``floor_rgb`` (module docstring); map-frame
    point p lies at ``rotation @ p + translation`` on the floor."""
    iy, ix = np.nonzero(np.asarray(texture.counts) > 0)
    observed = int(iy.size)
    if observed == 0:
        raise ValueError("the texture has no observed cell")
    if observed > max_cells:
        pick = np.linspace(0, observed - 1, max_cells).round().astype(np.int64)
        iy, ix = iy[pick], ix[pick]
    got = np.asarray(texture.colors)[iy, ix].astype(np.float64)
    res = texture.resolution_m
    x = texture.origin_x_m + (ix + 0.5) * res
    y = texture.origin_y_m + (iy + 0.5) * res
    offsets = ((np.arange(samples) + 0.5) / samples - 0.5) * res
    ox, oy = (o.ravel() for o in np.meshgrid(offsets, offsets))

    def error_per_cell(dx_cells: int, dy_cells: int) -> np.ndarray:
        px = (x[:, None] + dx_cells * res + ox[None, :]).ravel()
        py = (y[:, None] + dy_cells * res + oy[None, :]).ravel()
        wx = rotation[0, 0] * px + rotation[0, 1] * py + translation[0]
        wy = rotation[1, 0] * px + rotation[1, 1] * py + translation[1]
        truth = np.asarray(floor_rgb(wx, wy), dtype=np.float64).reshape(len(x), samples * samples, 3).mean(axis=1)
        if got.ndim == 1:
            return np.abs(got - truth @ _LUMINANCE)
        return np.abs(got - truth).mean(axis=1)

    at_zero = error_per_cell(0, 0)
    shifts = [(dx, dy) for dy in range(-max_shift_cells, max_shift_cells + 1)
              for dx in range(-max_shift_cells, max_shift_cells + 1)]
    # the texture at cell c shows the floor at c + shift: the truth sampled at c + shift fits best
    errors = [float(at_zero.mean()) if s == (0, 0) else float(error_per_cell(*s).mean()) for s in shifts]
    best = shifts[int(np.argmin(errors))]
    return TextureAccuracy(observed_cells=observed, scored_cells=int(x.size), colour_error_mean=float(at_zero.mean()),
                           colour_error_median=float(np.median(at_zero)), placement_offset_cells=best,
                           placement_offset_m=float(np.hypot(*best) * res), colour_error_at_offset=min(errors))
