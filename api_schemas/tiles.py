"""How a job's map tiles are laid out, so that a map client can place them (Leaflet ``L.CRS.Simple``)."""

from __future__ import annotations

from pydantic import BaseModel, Field


class TileSchemePublic(BaseModel):
    """The pyramid behind ``/v1/jobs/{id}/tiles/{layer}/{z}/{x}/{y}.png``.

    Zoom ``native_zoom`` is native resolution (one tile pixel per grid cell); each zoom below halves it;
    zoom 0 is the whole map in one tile. Tile (x, y) counts from the map's top-left corner, right and down.
    """

    job_id: str
    layer: str = Field(description="'occupancy' or 'texture'.")
    scheme: str = Field("simple", description="'simple': metric map frame, north up.")
    tile_size: int = Field(description="Tile width and height [px].")
    min_zoom: int
    max_zoom: int = Field(description="Deepest zoom that has tiles (= native_zoom).")
    native_zoom: int = Field(description="Zoom at which one tile pixel is one grid cell.")
    resolution_m: float = Field(description="Grid cell size [m].")
    top_left_m: list[float] = Field(description="Map-frame (x, y) of the map's top-left corner [m].")
    width_cells: int
    height_cells: int
    leaflet_transformation: list[float] = Field(
        description="(a, b, c, d) for L.Transformation on L.CRS.Simple, so that LatLng = [y_m, x_m].")
    scans_done: int = Field(description="Scans the map includes; changes while the job runs (cache key).")
