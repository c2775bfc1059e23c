"""ROS map_server / Nav2 map: an image plus a YAML file.

``mode: trinary`` (default): ``map.pgm`` with occupied 0, free 254, unknown 205 (the map_saver
values), thresholds as in :mod:`rendering`.
``mode: scale``: keeps the full probability range, grey = 255 * (1 - p). PGM has no way to mark a cell
unknown in scale mode, so the image is ``map.png`` with an alpha channel: unknown cells are grey 128
with alpha 0, which map_server and Nav2 load as unknown (-1).

YAML: ``image`` (relative to the YAML), ``resolution`` [m/cell], ``origin`` [x, y, yaw] = map-frame
pose of the image's lower-left pixel, ``negate: 0``, ``occupied_thresh``, ``free_thresh``, ``mode``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from slam_engine.errors import ConfigError
from slam_engine.model.result import OccupancyGrid
from slam_engine.products.files import atomic_path, write_text_atomic
from slam_engine.products.rendering import (
    FREE_THRESHOLD,
    OCCUPIED_THRESHOLD,
    ROS_FREE,
    ROS_OCCUPIED,
    ROS_UNKNOWN,
    OccupancyRasters,
    occupancy_north_up,
)

ROS_MODES = ("trinary", "scale")
_OCCUPIED, _FREE, _UNKNOWN = ROS_OCCUPIED, ROS_FREE, ROS_UNKNOWN


def ros_map_image(grid: OccupancyGrid, mode: str = "trinary", rasters: OccupancyRasters | None = None) -> Image.Image:
    """The map_server image of the grid ("L" for trinary, "LA" for scale), north up. ``rasters``:
    the grid's rasters when already made (trinary mode uses them)."""
    if mode == "trinary" and rasters is not None:
        return Image.fromarray(rasters.trinary)
    probability, known = occupancy_north_up(grid)
    if mode == "trinary":
        gray = np.full(probability.shape, _UNKNOWN, dtype=np.uint8)
        gray[known & (probability > OCCUPIED_THRESHOLD)] = _OCCUPIED
        gray[known & (probability < FREE_THRESHOLD)] = _FREE
        return Image.fromarray(gray)
    if mode == "scale":
        gray = np.where(known, np.rint(255.0 * (1.0 - probability)), 128).astype(np.uint8)
        alpha = np.where(known, 255, 0).astype(np.uint8)
        return Image.fromarray(np.dstack([gray, alpha]))
    raise ConfigError(f"ROS map mode {mode!r}: use one of {', '.join(ROS_MODES)}")


def write_ros_map(grid: OccupancyGrid, out_dir: str | Path, name: str = "map",
                  mode: str = "trinary", rasters: OccupancyRasters | None = None) -> tuple[Path, Path]:
    """Write ``NAME.pgm`` (trinary) or ``NAME.png`` (scale) and ``NAME.yaml`` into ``out_dir``;
    returns (image path, yaml path)."""
    out_dir = Path(out_dir)
    image = ros_map_image(grid, mode, rasters)
    image_path = out_dir / f"{name}.{'pgm' if mode == 'trinary' else 'png'}"
    with atomic_path(image_path) as tmp:
        image.save(tmp, format="PPM" if mode == "trinary" else "PNG")
    description = {
        "image": image_path.name,
        "mode": mode,
        "resolution": float(grid.resolution_m),
        "origin": [float(grid.origin_x_m), float(grid.origin_y_m), 0.0],
        "negate": 0,
        "occupied_thresh": OCCUPIED_THRESHOLD,
        "free_thresh": FREE_THRESHOLD,
    }
    yaml_path = write_text_atomic(out_dir / f"{name}.yaml", yaml.safe_dump(description, sort_keys=False))
    return image_path, yaml_path
