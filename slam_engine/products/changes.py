"""A change map's products: ``changes.png`` (the saved map with the cells added since in red and those
removed in blue) and ``changes.geojson`` (each changed region as a polygon of its cells' outline,
``kind`` added or removed, with its area).

GeoJSON coordinates are the saved map's frame [m] when the map is not placed on Earth (the map's own
frame, as the trajectory's); with a :class:`~slam_engine.products.georeference.Georeference` on
Earth they are WGS 84 longitude / latitude (RFC 7946), and each feature keeps its map-frame polygon
as ``properties.map_frame_geometry``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

from slam_engine.model.result import OccupancyGrid
from slam_engine.multisession.changes import ChangeMap
from slam_engine.products.files import atomic_path, write_text_atomic
from slam_engine.products.georeference import Georeference
from slam_engine.products.rendering import PNG_COMPRESS_LEVEL, occupancy_rasters

ADDED_RGB = (224, 49, 49)  # cells hit now where the saved map was free
REMOVED_RGB = (28, 126, 214)  # cells seen through now where the saved map held an obstacle
MAP_FRAME_NOTE = "the saved map's frame: x, y in m (not WGS 84: the map is not placed on Earth)"


def changes_image(saved: OccupancyGrid, changes: ChangeMap) -> Image.Image:
    """The saved map (north up, its own cells) with the added cells in red and the removed in blue."""
    image = np.array(Image.fromarray(occupancy_rasters(saved).gray).convert("RGB"))
    rows, cols = image.shape[:2]
    factor = max(1, int(round(changes.resolution_m / saved.resolution_m)))  # map cells a change cell spans
    for mask, colour in ((changes.removed, REMOVED_RGB), (changes.added, ADDED_RGB)):
        iy, ix = np.nonzero(mask)
        for dy in range(factor):
            for dx in range(factor):
                x, y = saved.world_to_cell(changes.origin_m[0] + (ix + (dx + 0.5) / factor) * changes.resolution_m,
                                           changes.origin_m[1] + (iy + (dy + 0.5) / factor) * changes.resolution_m)
                inside = (x >= 0) & (x < cols) & (y >= 0) & (y < rows)
                image[rows - 1 - y[inside], x[inside]] = colour  # row 0 of the image is the largest y
    return Image.fromarray(image)


def changes_geojson(changes: ChangeMap, georef: Georeference | None = None) -> dict:
    """The changed regions as a GeoJSON FeatureCollection (see the module docstring)."""
    from affine import Affine
    from rasterio import features

    transform = Affine(changes.resolution_m, 0.0, float(changes.origin_m[0]),
                       0.0, changes.resolution_m, float(changes.origin_m[1]))  # row = y, upwards
    on_earth = georef is not None and not georef.is_local
    out: list[dict] = []
    for kind, mask in (("added", changes.added), ("removed", changes.removed)):
        if not mask.any():
            continue
        for geometry, _ in features.shapes(mask.astype(np.uint8), mask=mask, transform=transform, connectivity=8):
            area = _area_m2(geometry)
            properties: dict = {"kind": kind, "area_m2": round(area, 3)}
            if on_earth:
                assert georef is not None
                properties["map_frame_geometry"] = geometry
                geometry = _lonlat(geometry, georef)
            out.append({"type": "Feature", "geometry": geometry, "properties": properties})
    doc: dict = {"type": "FeatureCollection", "features": out}
    if not on_earth:
        doc["coordinates"] = MAP_FRAME_NOTE
    return doc


def _area_m2(polygon: dict) -> float:
    """The area of a GeoJSON polygon (outer ring less its holes) [m^2]."""
    def ring_area(ring) -> float:
        xy = np.asarray(ring, np.float64)
        return 0.5 * abs(float(np.dot(xy[:-1, 0], xy[1:, 1]) - np.dot(xy[1:, 0], xy[:-1, 1])))

    rings = polygon["coordinates"]
    return ring_area(rings[0]) - sum(ring_area(r) for r in rings[1:])


def _lonlat(polygon: dict, georef: Georeference) -> dict:
    rings = []
    for ring in polygon["coordinates"]:
        xy = np.asarray(ring, np.float64)
        lon, lat = georef.map_to_lonlat(xy[:, 0], xy[:, 1])
        rings.append([[round(float(a), 8), round(float(b), 8)] for a, b in zip(lon, lat, strict=True)])
    return {"type": "Polygon", "coordinates": rings}


def write_changes(out_dir: str | Path, changes: ChangeMap, saved: OccupancyGrid,
                  georef: Georeference | None = None) -> dict[str, Path]:
    """``changes.png`` and ``changes.geojson`` in ``out_dir``; {name: path}."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "changes.png") as tmp:
        changes_image(saved, changes).save(tmp, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
    return {"changes.png": out / "changes.png",
            "changes.geojson": write_text_atomic(out / "changes.geojson",
                                                 json.dumps(changes_geojson(changes, georef)) + "\n")}
