"""GeoTIFF export with tifffile and the GeoTIFF tags GDAL/rasterio/QGIS read.

Tags written: ModelPixelScale, ModelTiepoint (north-up raster, pixel-is-area), GeoKeyDirectory
(+ GeoAsciiParams), and GDAL_NODATA for the occupancy rasters.
- local map frame: an engineering CRS, written the way GDAL writes a ``LOCAL_CS`` (citation + metre
  units, no model type); rasterio reads it back as ``LOCAL_CS["lidarmap local map frame", ...]``.
- UTM: ``ProjectedCSTypeGeoKey`` = the EPSG code (326xx / 327xx).

Occupancy values: ``"probability"`` float32 in [0, 1], or ``"percent"`` int8 0..100; either way
unknown (and outside the map after a UTM resample) is -1, the declared nodata value.
Texture: RGBA uint8, alpha 0 where the ground was never seen (GDAL reads band 4 as alpha).
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
import tifffile

from slam_engine.errors import ConfigError
from slam_engine.model.result import OccupancyGrid, TextureMap
from slam_engine.products.files import atomic_path
from slam_engine.products.georeference import Georeference, NorthUpRaster, north_up_raster
from slam_engine.products.rendering import OccupancyRasters, occupancy_north_up, probability_band, texture_north_up

NODATA = -1
OCCUPANCY_KINDS = ("probability", "percent")

# GeoKey ids and codes (GeoTIFF 1.1).
_GT_MODEL_TYPE, _GT_RASTER_TYPE, _GT_CITATION = 1024, 1025, 1026
_PROJECTED_CS_TYPE, _PROJ_LINEAR_UNITS = 3072, 3076
_MODEL_TYPE_PROJECTED, _RASTER_PIXEL_IS_AREA, _LINEAR_METRE = 1, 1, 9001
_GEO_ASCII_PARAMS_TAG = 34737
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
    local frame the probability raster is computed and compressed strip by strip as it is written
    (never whole: 4 bytes a cell)."""
    georef = georef or Georeference.local()
    if kind == "probability" and georef.is_local:
        h, w = grid.shape
        strips = (zlib.compress(probability_band(grid, r0, min(h, r0 + ROWS_PER_STRIP)).tobytes(), ZLIB_LEVEL)
                  for r0 in range(0, h, ROWS_PER_STRIP))
        raster = NorthUpRaster(strips, grid.origin_x_m, grid.origin_y_m + h * grid.resolution_m,  # type: ignore[arg-type]
                               grid.resolution_m)
        return _write(path, raster, georef, photometric="minisblack", nodata=NODATA,
                      shape=(h, w), dtype=np.float32, rowsperstrip=ROWS_PER_STRIP)
    values = occupancy_values(grid, kind, rasters)
    raster = north_up_raster(values, grid.resolution_m, grid.origin_x_m, grid.origin_y_m, georef, NODATA)
    return _write(path, raster, georef, photometric="minisblack", nodata=NODATA)


def write_texture_geotiff(texture: TextureMap, path: str | Path, georef: Georeference | None = None) -> Path:
    """Write the texture as an RGBA GeoTIFF (alpha 0 = never seen); returns the path."""
    georef = georef or Georeference.local()
    colors, seen = texture_north_up(texture)
    rgba = np.dstack([colors, np.where(seen, np.uint8(255), np.uint8(0))])
    raster = north_up_raster(rgba, texture.resolution_m, texture.origin_x_m, texture.origin_y_m, georef,
                             np.zeros(4, dtype=np.uint8))
    return _write(path, raster, georef, photometric="rgb", nodata=None, extrasamples=(2,))


def _geokeys(georef: Georeference) -> tuple[list[int], str]:
    """GeoKeyDirectory entries and the GeoAsciiParams string."""
    citation = georef.crs_name + "|"
    keys = [(_GT_RASTER_TYPE, 0, 1, _RASTER_PIXEL_IS_AREA),
            (_GT_CITATION, _GEO_ASCII_PARAMS_TAG, len(citation), 0)]
    if georef.epsg is not None:
        keys += [(_GT_MODEL_TYPE, 0, 1, _MODEL_TYPE_PROJECTED), (_PROJECTED_CS_TYPE, 0, 1, georef.epsg)]
    keys.append((_PROJ_LINEAR_UNITS, 0, 1, _LINEAR_METRE))
    keys.sort()
    directory = [1, 1, 0, len(keys)] + [v for key in keys for v in key]
    return directory, citation


def _write(path: str | Path, raster: NorthUpRaster, georef: Georeference, photometric: str,
           nodata: int | None, extrasamples: tuple[int, ...] = (), **strips) -> Path:
    """``strips``: ``shape``, ``dtype`` and ``rowsperstrip`` where ``raster.values`` is an iterator
    of zlib-compressed strips instead of an array."""
    directory, citation = _geokeys(georef)
    tags = [
        (33550, "d", 3, (raster.pixel_m, raster.pixel_m, 0.0), True),  # ModelPixelScale
        (33922, "d", 6, (0.0, 0.0, 0.0, raster.left_m, raster.top_m, 0.0), True),  # ModelTiepoint
        (34735, "H", len(directory), directory, True),  # GeoKeyDirectory
        (_GEO_ASCII_PARAMS_TAG, "s", 0, citation, True),
    ]
    if nodata is not None:
        tags.append((42113, "s", 0, str(nodata), True))  # GDAL_NODATA
    with atomic_path(path) as tmp:
        tifffile.imwrite(tmp, raster.values, photometric=photometric, extrasamples=extrasamples or None,
                         compression="zlib", compressionargs=None if strips else {"level": ZLIB_LEVEL},
                         extratags=tags, metadata=None, **strips)
    return Path(path)
