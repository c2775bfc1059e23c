"""Placing the map frame on Earth (UTM) or in a local metric frame, and resampling rasters north up.

Without a geo origin the products use the *local map frame*: x east-ish, y north-ish, metres, origin
at the map frame's origin (the first pose); GeoTIFFs carry a local engineering CRS
(``LOCAL_CS``) with pixel = grid resolution.

With a :class:`GeoOrigin` (latitude, longitude and compass heading of the first pose) the map frame
is placed in the WGS 84 UTM zone of the start (EPSG:326xx north, 327xx south): the map is rotated by
the heading (and the zone's meridian convergence) and scaled by the zone's scale factor, all read off
pyproj's geodesic and projection at the start, so ``crs = A @ map + b`` near the run.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from slam_engine.errors import ConfigError

if TYPE_CHECKING:  # pyproj (~12 MB) is imported only where a geo origin is given
    from pyproj import Transformer

LOCAL_CRS_NAME = "lidarmap local map frame"
WEB_MERCATOR_EPSG = 3857
_AXIS_PROBE_M = 10.0  # geodesic probe length used to measure the map axes in UTM [m]


@dataclass(frozen=True)
class GeoOrigin:
    """Where the run started: WGS 84 latitude / longitude [deg] of the first pose, and the heading
    [deg, clockwise from true north] the vehicle's x axis (forward) pointed at that pose."""

    latitude_deg: float
    longitude_deg: float
    heading_deg: float = 0.0

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.latitude_deg, self.longitude_deg, self.heading_deg)):
            raise ConfigError("geo origin: latitude, longitude and heading must be finite numbers")
        if not -80.0 <= self.latitude_deg <= 84.0:
            raise ConfigError(f"geo origin: latitude {self.latitude_deg} deg is outside the UTM "
                              "domain [-80, 84]")
        if not -180.0 <= self.longitude_deg <= 180.0:
            raise ConfigError(f"geo origin: longitude {self.longitude_deg} deg is outside [-180, 180]")


@dataclass(frozen=True)
class Georeference:
    """Affine placement ``[easting, northing] = A @ [x_m, y_m] + b`` of the map frame in a CRS.

    ``epsg`` is None for the local map frame (A = identity, b = 0)."""

    A: np.ndarray
    b: np.ndarray
    epsg: int | None
    crs_name: str

    @classmethod
    def local(cls) -> Georeference:
        """The local metric map frame itself."""
        return cls(A=np.eye(2), b=np.zeros(2), epsg=None, crs_name=LOCAL_CRS_NAME)

    @classmethod
    def utm(cls, origin: GeoOrigin, start_pose: np.ndarray | Sequence[float]) -> Georeference:
        """UTM placement given the geo origin of ``start_pose`` = [x_m, y_m, theta_rad] (map frame)."""
        from pyproj import CRS, Geod

        epsg = utm_epsg(origin.latitude_deg, origin.longitude_deg)
        to_utm = _transformer(4326, epsg)
        geod = Geod(ellps="WGS84")
        e0, n0 = to_utm.transform(origin.longitude_deg, origin.latitude_deg)
        columns = []
        for azimuth_deg in (origin.heading_deg, origin.heading_deg - 90.0):  # vehicle forward, left
            lon, lat, _ = geod.fwd(origin.longitude_deg, origin.latitude_deg, azimuth_deg, _AXIS_PROBE_M)
            e, n = to_utm.transform(lon, lat)
            columns.append([(e - e0) / _AXIS_PROBE_M, (n - n0) / _AXIS_PROBE_M])
        J_utm_from_vehicle = np.array(columns).T
        x0, y0, theta0 = (float(v) for v in start_pose)
        R_vehicle_from_map = np.array([[math.cos(theta0), math.sin(theta0)],
                                       [-math.sin(theta0), math.cos(theta0)]])
        A = J_utm_from_vehicle @ R_vehicle_from_map
        b = np.array([e0, n0]) - A @ np.array([x0, y0])
        return cls(A=A, b=b, epsg=epsg, crs_name=CRS.from_epsg(epsg).name)

    @property
    def is_local(self) -> bool:
        return self.epsg is None

    def map_to_crs(self, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """CRS coordinates (easting, northing) [m] of map-frame points."""
        x_m, y_m = np.asarray(x_m, dtype=np.float64), np.asarray(y_m, dtype=np.float64)
        return (self.A[0, 0] * x_m + self.A[0, 1] * y_m + self.b[0],
                self.A[1, 0] * x_m + self.A[1, 1] * y_m + self.b[1])

    def crs_to_map(self, e: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map-frame coordinates [m] of CRS points."""
        inv = np.linalg.inv(self.A)
        de, dn = np.asarray(e, dtype=np.float64) - self.b[0], np.asarray(n, dtype=np.float64) - self.b[1]
        return inv[0, 0] * de + inv[0, 1] * dn, inv[1, 0] * de + inv[1, 1] * dn

    def web_mercator_to_map(self, mx: np.ndarray, my: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map-frame coordinates [m] of Web Mercator (EPSG:3857) points; needs a UTM placement."""
        if self.epsg is None:
            raise ConfigError("Web Mercator needs a geo origin (latitude, longitude, heading)")
        e, n = _transformer(WEB_MERCATOR_EPSG, self.epsg).transform(mx, my)
        return self.crs_to_map(e, n)

    def map_to_lonlat(self, x_m: np.ndarray, y_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """WGS 84 (longitude, latitude) [deg] of map-frame points; needs a UTM placement."""
        if self.epsg is None:
            raise ConfigError("longitude/latitude need a geo origin (latitude, longitude, heading)")
        e, n = self.map_to_crs(x_m, y_m)
        return _transformer(self.epsg, 4326).transform(e, n)

    def describe(self) -> dict:
        """JSON-ready summary (for run.json)."""
        return {"crs": self.crs_name, "epsg": self.epsg,
                "A_crs_from_map": self.A.tolist(), "b_crs_m": self.b.tolist()}


def utm_epsg(latitude_deg: float, longitude_deg: float) -> int:
    """EPSG code of the WGS 84 UTM zone containing the point (326xx north, 327xx south; the
    Norway and Svalbard exceptions included), from the PROJ database."""
    from pyproj.aoi import AreaOfInterest
    from pyproj.database import query_utm_crs_info

    infos = query_utm_crs_info(datum_name="WGS 84", area_of_interest=AreaOfInterest(
        longitude_deg, latitude_deg, longitude_deg, latitude_deg))
    prefix = "326" if latitude_deg >= 0.0 else "327"
    codes = sorted(int(i.code) for i in infos if i.auth_name == "EPSG" and i.code.startswith(prefix))
    if not codes:
        raise ConfigError(f"no WGS 84 UTM zone for latitude {latitude_deg}, longitude {longitude_deg}")
    return codes[0]


@functools.lru_cache(maxsize=32)
def _transformer(src_epsg: int, dst_epsg: int) -> Transformer:
    from pyproj import Transformer

    return Transformer.from_crs(src_epsg, dst_epsg, always_xy=True)


@dataclass(frozen=True)
class NorthUpRaster:
    """A raster aligned with the CRS axes: ``values[row, col]``; pixel (col, row)'s top-left corner
    is at (left_m + col * pixel_m, top_m - row * pixel_m)."""

    values: np.ndarray
    left_m: float
    top_m: float
    pixel_m: float


def north_up_raster(values: np.ndarray, resolution_m: float, origin_x_m: float, origin_y_m: float,
                    georef: Georeference, fill) -> NorthUpRaster:
    """Resample a north-up map image ``values`` (H, W[, C]) (row 0 = largest y) into ``georef``'s CRS,
    north up, pixel = ``resolution_m``, nearest cell; pixels outside the map get ``fill``.

    In the local frame this is the image itself, untouched."""
    h, w = values.shape[:2]
    top_y = origin_y_m + h * resolution_m
    if georef.is_local:
        return NorthUpRaster(values, origin_x_m, top_y, resolution_m)
    corners_x = np.array([origin_x_m, origin_x_m + w * resolution_m] * 2)
    corners_y = np.array([origin_y_m] * 2 + [top_y] * 2)
    e, n = georef.map_to_crs(corners_x, corners_y)
    px = resolution_m
    left, top = math.floor(e.min() / px) * px, math.ceil(n.max() / px) * px
    out_w, out_h = math.ceil((e.max() - left) / px), math.ceil((top - n.min()) / px)
    cols, rows = np.meshgrid(np.arange(out_w), np.arange(out_h))
    x, y = georef.crs_to_map(left + (cols + 0.5) * px, top - (rows + 0.5) * px)
    ix = np.floor((x - origin_x_m) / resolution_m).astype(np.int64)
    iy = np.floor((y - origin_y_m) / resolution_m).astype(np.int64)
    inside = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    src_row = np.where(inside, h - 1 - iy, 0)
    src_col = np.where(inside, ix, 0)
    out = values[src_row, src_col]
    mask = inside if out.ndim == 2 else inside[..., None]
    return NorthUpRaster(np.where(mask, out, np.asarray(fill, dtype=values.dtype)), left, top, px)
