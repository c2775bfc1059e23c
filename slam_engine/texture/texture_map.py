"""Per-cell ground colour accumulation on the occupancy grid's geometry.

The texture has exactly the grid's shape, resolution and origin, so texture cell (ix, iy) is grid
cell (ix, iy); ground points that fall outside the grid are counted and dropped.
"""

from __future__ import annotations

import numpy as np

from slam_engine.model.result import OccupancyGrid, TextureMap

CELL_MODES = ("mean", "latest")


class TextureAccumulator:
    """Colours of ground points binned into grid cells.

    ``mode="mean"``: each cell holds the running mean of every point that fell in it.
    ``mode="latest"``: each cell holds the mean colour of the latest frame that saw it.
    ``channels`` is 3 (RGB) or 1 (gray); colours of the other kind are converted on the way in.
    """

    def __init__(self, grid: OccupancyGrid, channels: int, mode: str = "mean"):
        if mode not in CELL_MODES:
            raise ValueError(f"cell mode {mode!r}, expected one of {CELL_MODES}")
        if channels not in (1, 3):
            raise ValueError(f"channels {channels}, expected 1 or 3")
        self.grid = grid
        self.channels = channels
        self.mode = mode
        height, width = grid.shape
        self._mean = np.zeros((height * width, channels), dtype=np.float32)
        self._counts = np.zeros(height * width, dtype=np.int64)
        self.points_added = 0
        self.points_outside = 0

    def add(self, x_m: np.ndarray, y_m: np.ndarray, colors: np.ndarray) -> None:
        """Add one frame's ground points: map-frame ``x_m``, ``y_m`` (N,) and ``colors`` (N, 3) or (N,)."""
        colors = self._as_channels(np.asarray(colors))
        ix, iy = self.grid.world_to_cell(x_m, y_m)
        height, width = self.grid.shape
        inside = (ix >= 0) & (ix < width) & (iy >= 0) & (iy < height)
        self.points_outside += int(np.count_nonzero(~inside))
        if not inside.any():
            return
        ix, iy, colors = ix[inside], iy[inside], colors[inside]
        self.points_added += int(ix.size)
        # binned within the frame's bounding box: cells come out in the grid's row-major order, and
        # each cell's colours are summed in the order given
        x0, y0 = int(ix.min()), int(iy.min())
        box_w = int(ix.max()) - x0 + 1
        local = (iy - y0) * box_w + (ix - x0)
        box_counts = np.bincount(local)
        in_box = np.flatnonzero(box_counts)
        frame_counts = box_counts[in_box]
        cells = (in_box // box_w + y0) * width + in_box % box_w + x0
        frame_sums = np.stack([np.bincount(local, weights=colors[:, c])[in_box] for c in range(self.channels)],
                              axis=-1)
        frame_mean = frame_sums / frame_counts[:, None]
        if self.mode == "latest":
            self._mean[cells] = frame_mean
        else:
            total = self._counts[cells] + frame_counts
            old = self._mean[cells].astype(np.float64)
            self._mean[cells] = old + (frame_mean - old) * (frame_counts / total)[:, None]
        self._counts[cells] += frame_counts

    def texture_map(self) -> TextureMap:
        """The accumulated :class:`TextureMap`: (H, W, 3) RGB or (H, W) gray uint8, unseen cells 0."""
        height, width = self.grid.shape
        seen = np.flatnonzero(self._counts)  # only these cells hold a colour: the others stay 0
        flat = np.zeros((height * width, self.channels), dtype=np.uint8)
        flat[seen] = np.clip(np.rint(self._mean[seen]), 0, 255).astype(np.uint8)
        colors = flat.reshape(height, width, self.channels)
        if self.channels == 1:
            colors = colors[:, :, 0]
        counts = np.minimum(self._counts, np.iinfo(np.int32).max).astype(np.int32).reshape(height, width)
        return TextureMap(colors=colors, counts=counts, resolution_m=self.grid.resolution_m,
                          origin_x_m=self.grid.origin_x_m, origin_y_m=self.grid.origin_y_m)

    def _as_channels(self, colors: np.ndarray) -> np.ndarray:
        colors = colors.astype(np.float64)
        if colors.ndim == 1:
            colors = colors[:, None]
        if colors.shape[1] == self.channels:
            return colors
        if self.channels == 3:  # gray into an RGB map
            return np.repeat(colors[:, :1], 3, axis=1)
        luma = colors @ np.array([0.299, 0.587, 0.114])  # RGB into a gray map (ITU-R BT.601)
        return luma[:, None]
