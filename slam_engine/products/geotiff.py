"""GeoTIFF export through rasterio (GDAL): files that GDAL, rasterio (`rio info`) and QGIS read.

- with a geo origin: the WGS 84 UTM zone of the start (EPSG:326xx / 327xx), north up;
- in the local map frame: no CRS (there is no transformation from the map frame to any Earth CRS,
  and a CRS that GDAL cannot transform, such as an engineering ``LOCAL_CS``, makes ``rio info`` fail),
  only the affine transform, in metres of the map frame; the frame is named in the file's metadata
  (tag ``LIDARMAP_FRAME``).

Occupancy values: ``"probability"`` float32 in [0, 1], or ``"percent"`` int8 0..100; either way
unknown (and outside the map after a UTM resample) is -1, the declared nodata value.
Texture: RGBA uint8, alpha 0 where the ground was never seen (band 4 is declared alpha).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from slam_engine.errors import ConfigError
from slam_engine.model.result import OccupancyGrid, TextureMap
from slam_engine.products.files import atomic_path
from slam_engine.products.georeference import Georeference, NorthUpRaster, north_up_raster
from slam_engine.products.rendering import OccupancyRasters, occupancy_north_up, probability_band, texture_north_up

NODATA = -1
OCCUPANCY_KINDS = ("probability", "percent")

ZLIB_LEVEL = 1  # 3x faster than zlib's default 6 on an occupancy raster, the file ~40 % larger
ROWS_PER_STRIP = 256  # the local-frame probability GeoTIFF is computed and written this many rows at a time


def occupancy_values(grid: OccupancyGrid, kind: str = "probability",
                     rasters: OccupancyRasters | None = None) -> np.ndarray:
    """North-up raster values of the grid: float32 probability or int8 percent, -1 where unknown
    (``rasters``: accepted for compatibility; the values are computed from the grid)."""
    if kind not in OCCUPANCY_KINDS:
        raise ConfigError(f"occupancy GeoTIFF kind {kind!r}: use one of {', '.join(OCCUPANCY_KINDS)}")
    if kind == "probability":
        h = grid.shape[0]
        return np.concatenate([probability_band(grid, r0, min(h, r0 + ROWS_PER_STRIP))
                               for r0 in range(0, h, ROWS_PER_STRIP)])
    probability, known = occupancy_north_up(grid)
    if kind == "probability":
        return np.where(known, probability, NODATA).astype(np.float32)
    return np.where(known, np.rint(100.0 * probability), NODATA).astype(np.int8)


def write_occupancy_geotiff(grid: OccupancyGrid, path: str | Path, georef: Georeference | None = None,
                            kind: str = "probability", rasters: OccupancyRasters | None = None) -> Path:
    """Write the grid as a single-band GeoTIFF (see module docstring); returns the path. In the
    local frame the probability raster is computed and written strip by strip (never whole: 4 bytes
    a cell)."""
    georef = georef or Georeference.local()
    if kind == "probability" and georef.is_local:
        h, w = grid.shape
        strips = (probability_band(grid, r0, min(h, r0 + ROWS_PER_STRIP)) for r0 in range(0, h, ROWS_PER_STRIP))
        top_m = grid.origin_y_m + h * grid.resolution_m
        return _write(path, strips, (h, w, 1), np.dtype(np.float32), grid.origin_x_m, top_m, grid.resolution_m,
                      georef, nodata=NODATA)
    values = occupancy_values(grid, kind, rasters)
    raster = north_up_raster(values, grid.resolution_m, grid.origin_x_m, grid.origin_y_m, georef, NODATA)
    return _write_raster(path, raster, georef, nodata=NODATA)


def write_texture_geotiff(texture: TextureMap, path: str | Path, georef: Georeference | None = None) -> Path:
    """Write the texture as an RGBA GeoTIFF (alpha 0 = never seen); returns the path."""
    georef = georef or Georeference.local()
    colors, seen = texture_north_up(texture)
    rgba = np.dstack([colors, np.where(seen, np.uint8(255), np.uint8(0))])
    raster = north_up_raster(rgba, texture.resolution_m, texture.origin_x_m, texture.origin_y_m, georef,
                             np.zeros(4, dtype=np.uint8))
    return _write_raster(path, raster, georef, nodata=None, photometric="RGB", alpha="YES")


def _write_raster(path: str | Path, raster: NorthUpRaster, georef: Georeference, nodata: int | None,
                  **creation: str) -> Path:
    values = raster.values if raster.values.ndim == 3 else raster.values[..., None]
    return _write(path, iter([values]), values.shape, values.dtype, raster.left_m, raster.top_m, raster.pixel_m,
                  georef, nodata, **creation)


def _write(path: str | Path, strips: Iterator[np.ndarray], shape: tuple[int, ...], dtype: np.dtype,
           left_m: float, top_m: float, pixel_m: float, georef: Georeference, nodata: int | None,
           **creation: str) -> Path:
    """Write ``strips`` (row blocks of ``shape`` = (H, W, bands), top first) north up: pixel (col, row)'s
    top-left corner at (left_m + col * pixel_m, top_m - row * pixel_m) in ``georef``'s CRS."""
    import rasterio
    from affine import Affine
    from rasterio.crs import CRS
    from rasterio.windows import Window

    h, w, bands = (*shape[:2], 1 if len(shape) == 2 else shape[2])
    profile: dict[str, Any] = {
        "driver": "GTiff", "width": w, "height": h, "count": bands, "dtype": np.dtype(dtype).name,
        "crs": None if georef.epsg is None else CRS.from_epsg(georef.epsg),
        "transform": Affine.translation(left_m, top_m) @ Affine.scale(pixel_m, -pixel_m), "nodata": nodata,
        "compress": "deflate", "zlevel": ZLIB_LEVEL, "blockysize": min(h, ROWS_PER_STRIP), **creation}
    with atomic_path(path) as tmp, rasterio.open(tmp, "w", **profile) as dst:
        dst.update_tags(AREA_OR_POINT="Area", LIDARMAP_FRAME=georef.crs_name)
        row = 0
        for strip in strips:
            block = strip if strip.ndim == 3 else strip[..., None]
            dst.write(np.moveaxis(block, -1, 0), window=Window(0, row, w, block.shape[0]))
            row += block.shape[0]
    return Path(path)
