"""Map tiles (256 x 256 PNG), rendered on demand from the grid or the texture, with an LRU cache.

Simple scheme (``scheme="simple"``, for Leaflet ``L.CRS.Simple``), see :class:`TileScheme`:
- zoom ``max_zoom`` is native resolution: one tile pixel = one grid cell; each zoom level below halves
  the resolution (pixel = 2^(max_zoom - z) cells); z = 0 is the whole map in one tile.
- tile (x, y) = (column, row), counted from the map's top-left corner (smallest x, largest y of the
  grid) to the right and down; the pyramid ends at the last tile touching the map (others: error).
- Zoomed-out pixels keep obstacles: a pixel shows the highest occupancy among its known cells.
- Pixels outside the grid are transparent; unknown cells are grey (205), as in ``occupancy.png``.
- In Leaflet, ``L.extend({}, L.CRS.Simple, {transformation: new L.Transformation(a, b, c, d)})`` with
  ``(a, b, c, d) = scheme.leaflet_transformation()`` makes LatLng = [y_m, x_m] in the map frame.

Web Mercator scheme (``scheme="webmercator"``, needs a :class:`Georeference` in UTM): the usual
XYZ/slippy tiles (EPSG:3857, y counted down from the north); zooms 0 .. the first zoom whose pixel is no
larger than a grid cell; x/y limited to the tiles touching the map. Resampled nearest from the
pooled grid.

Texture tiles: mean colour of the seen cells, transparent where the ground was never seen.

The map may be a :class:`~slam_engine.products.tile_pyramid.TilePyramid` (a file read by window): a tile
then reads at most its own window of one pooled level, whatever the map's size.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass

import numpy as np
from PIL import Image

from slam_engine.errors import ConfigError, TileOutOfRangeError
from slam_engine.model.result import OccupancyGrid, TextureMap
from slam_engine.products.georeference import Georeference, _transformer
from slam_engine.products.rendering import occupancy_gray, png_bytes, pool_occupancy, pool_texture
from slam_engine.products.tile_pyramid import TILE_SIZE, TilePyramid

SCHEMES = ("simple", "webmercator")
WEB_MERCATOR_HALF_WORLD_M = 20037508.342789244  # pi * 6378137
MAX_CACHED_TILE_BYTES = 32 * 1024**2  # the rendered tiles kept, in bytes of PNG

MapSource = OccupancyGrid | TextureMap | TilePyramid  # a pyramid: read by window, never whole


@dataclass(frozen=True)
class TileScheme:
    """The simple-CRS pyramid of one map: ``width`` x ``height`` cells of ``resolution_m``, whose
    top-left corner is at (``left_m``, ``top_m``) in the map frame."""

    width: int
    height: int
    resolution_m: float
    left_m: float
    top_m: float

    @classmethod
    def for_map(cls, source: MapSource) -> TileScheme:
        h, w = _shape(source)
        return cls(width=w, height=h, resolution_m=float(source.resolution_m),
                   left_m=float(source.origin_x_m), top_m=float(source.origin_y_m + h * source.resolution_m))

    @property
    def max_zoom(self) -> int:
        """Native zoom: one tile pixel per cell."""
        return max(0, math.ceil(math.log2(max(self.width, self.height, 1) / TILE_SIZE)))

    def cells_per_pixel(self, z: int) -> int:
        return 2 ** (self.max_zoom - z)

    def metres_per_pixel(self, z: int) -> float:
        return self.resolution_m * self.cells_per_pixel(z)

    def tile_counts(self, z: int) -> tuple[int, int]:
        """(columns, rows) of tiles at zoom ``z``."""
        span = TILE_SIZE * self.cells_per_pixel(z)
        return math.ceil(self.width / span), math.ceil(self.height / span)

    def check(self, z: int, x: int, y: int) -> None:
        """Raise :class:`TileOutOfRangeError` unless tile z/x/y exists."""
        if not 0 <= z <= self.max_zoom:
            raise TileOutOfRangeError(f"zoom {z} outside 0..{self.max_zoom}")
        nx, ny = self.tile_counts(z)
        if not (0 <= x < nx and 0 <= y < ny):
            raise TileOutOfRangeError(f"tile {z}/{x}/{y} outside x 0..{nx - 1}, y 0..{ny - 1} at zoom {z}")

    def leaflet_transformation(self) -> tuple[float, float, float, float]:
        """(a, b, c, d) for ``L.Transformation`` so that LatLng [y_m, x_m] lands on these tiles."""
        m0 = self.metres_per_pixel(0)
        return 1.0 / m0, -self.left_m / m0, -1.0 / m0, self.top_m / m0

    def describe(self) -> dict:
        """JSON-ready description for clients."""
        return {"scheme": "simple", "tile_size": TILE_SIZE, "min_zoom": 0, "max_zoom": self.max_zoom,
                "native_zoom": self.max_zoom, "resolution_m": self.resolution_m,
                "top_left_m": [self.left_m, self.top_m], "width_cells": self.width, "height_cells": self.height,
                "leaflet_transformation": list(self.leaflet_transformation())}


@dataclass(frozen=True)
class WebMercatorScheme:
    """XYZ tiles of a georeferenced map: bounds in EPSG:3857 metres and the native zoom."""

    min_x_m: float
    min_y_m: float
    max_x_m: float
    max_y_m: float
    max_zoom: int

    @classmethod
    def for_map(cls, source: MapSource, georef: Georeference | None) -> WebMercatorScheme:
        if georef is None or georef.is_local:
            raise ConfigError("Web Mercator tiles need a geo origin (latitude, longitude, heading)")
        h, w = _shape(source)
        xs = source.origin_x_m + np.array([0, w, 0, w]) * source.resolution_m
        ys = source.origin_y_m + np.array([0, 0, h, h]) * source.resolution_m
        e, n = georef.map_to_crs(xs, ys)
        mx, my = _transformer(georef.epsg, 3857).transform(e, n)
        lon, lat = _transformer(georef.epsg, 4326).transform(e.mean(), n.mean())
        ground_per_world_pixel = 2 * WEB_MERCATOR_HALF_WORLD_M * math.cos(math.radians(lat)) / TILE_SIZE
        max_zoom = max(0, math.ceil(math.log2(ground_per_world_pixel / source.resolution_m)))
        return cls(float(mx.min()), float(my.min()), float(mx.max()), float(my.max()), max_zoom)

    @staticmethod
    def tile_m(z: int) -> float:
        return 2 * WEB_MERCATOR_HALF_WORLD_M / 2**z

    def ground_m(self, mercator_m: float) -> float:
        """Ground length [m] of a Web Mercator length at the map's latitude."""
        latitude_rad = math.atan(math.sinh(0.5 * (self.min_y_m + self.max_y_m) / 6378137.0))
        return mercator_m * math.cos(latitude_rad)

    def tile_range(self, z: int) -> tuple[int, int, int, int]:
        """(x_min, x_max, y_min, y_max) tile indices touching the map at zoom ``z`` (inclusive)."""
        t = self.tile_m(z)
        last = 2**z - 1

        def clamp(v: float) -> int:
            return min(max(math.floor(v), 0), last)

        return (clamp((self.min_x_m + WEB_MERCATOR_HALF_WORLD_M) / t),
                clamp((self.max_x_m + WEB_MERCATOR_HALF_WORLD_M) / t),
                clamp((WEB_MERCATOR_HALF_WORLD_M - self.max_y_m) / t),
                clamp((WEB_MERCATOR_HALF_WORLD_M - self.min_y_m) / t))

    def check(self, z: int, x: int, y: int) -> None:
        if not 0 <= z <= self.max_zoom:
            raise TileOutOfRangeError(f"zoom {z} outside 0..{self.max_zoom}")
        x0, x1, y0, y1 = self.tile_range(z)
        if not (x0 <= x <= x1 and y0 <= y <= y1):
            raise TileOutOfRangeError(f"tile {z}/{x}/{y} outside x {x0}..{x1}, y {y0}..{y1} at zoom {z}")


def render_tile(source: MapSource, z: int, x: int, y: int, layer: str | None = None, *,
                scheme: str = "simple", georef: Georeference | None = None,
                map_version: Hashable | None = None) -> bytes:
    """One 256 x 256 RGBA PNG tile of ``source`` (an OccupancyGrid or a TextureMap).

    ``layer`` ("occupancy" / "texture") is optional and must match the source. With ``map_version``
    (anything hashable that changes whenever the map does, e.g. (job id, scans done)) tiles are kept
    in a process-wide LRU cache. Raises :class:`TileOutOfRangeError` for tiles outside the pyramid.
    """
    layer = _layer(source, layer)
    if scheme not in SCHEMES:
        raise ConfigError(f"tile scheme {scheme!r}: use one of {', '.join(SCHEMES)}")
    key = None if map_version is None else (map_version, layer, scheme, z, x, y)
    if key is not None:
        cached = _CACHE.get(key)
        if cached is not None:
            return cached
    rgba = _simple_tile(source, z, x, y) if scheme == "simple" else _web_mercator_tile(source, georef, z, x, y)
    png = png_bytes(Image.fromarray(rgba))
    if key is not None:
        _CACHE.put(key, png)
    return png


def map_image_at_zoom(source: OccupancyGrid | TextureMap, z: int) -> np.ndarray:
    """The whole map at simple-scheme zoom ``z`` as an RGBA array (what the tiles at z show, stitched)."""
    scheme = TileScheme.for_map(source)
    if not 0 <= z <= scheme.max_zoom:
        raise TileOutOfRangeError(f"zoom {z} outside 0..{scheme.max_zoom}")
    window = _window(source, 0, scheme.height, 0, scheme.width)
    return _shade(source, _pool(source, window, scheme.cells_per_pixel(z)))


class _LruCache:
    """Thread-safe least-recently-used cache of tile bytes, bounded in bytes."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self.bytes = 0
        self._items: OrderedDict[Hashable, bytes] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Hashable) -> bytes | None:
        with self._lock:
            value = self._items.get(key)
            if value is not None:
                self._items.move_to_end(key)
            return value

    def put(self, key: Hashable, value: bytes) -> None:
        if len(value) > self.max_bytes:
            return
        with self._lock:
            old = self._items.pop(key, None)
            self.bytes += len(value) - (len(old) if old is not None else 0)
            self._items[key] = value
            while self.bytes > self.max_bytes:
                _, dropped = self._items.popitem(last=False)
                self.bytes -= len(dropped)

    def __len__(self) -> int:
        return len(self._items)


_CACHE = _LruCache(MAX_CACHED_TILE_BYTES)


def _layer(source: MapSource, layer: str | None) -> str:
    actual = "occupancy" if isinstance(source, OccupancyGrid) else "texture" if isinstance(source, TextureMap) \
        else source.layer if isinstance(source, TilePyramid) else None
    if actual is None:
        raise ConfigError(f"tiles are made from an OccupancyGrid, a TextureMap or a TilePyramid, not "
                          f"{type(source).__name__}")
    if layer is not None and layer != actual:
        raise ConfigError(f"layer {layer!r} does not match the map given ({actual})")
    return actual


def _shape(source: MapSource) -> tuple[int, int]:
    if isinstance(source, TilePyramid):
        return source.shape
    return source.log_odds.shape if isinstance(source, OccupancyGrid) else np.asarray(source.counts).shape


def _window(source: OccupancyGrid | TextureMap, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, ...]:
    """North-up window rows [r0, r1), cols [c0, c1) of the map (may reach outside it): for a grid
    (log_odds, known, inside), for a texture (colors, seen, inside); outside cells padded."""
    h, w = _shape(source)
    rr0, rr1, cc0, cc1 = max(r0, 0), min(max(r1, 0), h), max(c0, 0), min(max(c1, 0), w)
    rr1, cc1 = max(rr1, rr0), max(cc1, cc0)
    iy0, iy1 = h - rr1, h - rr0  # grid rows of the window, bottom-up
    if isinstance(source, OccupancyGrid):
        log_odds = np.flipud(source.log_odds[iy0:iy1, cc0:cc1])
        parts = [log_odds, log_odds != 0.0]
        fills = [0.0, False]
    else:
        colors = np.asarray(source.colors)[iy0:iy1, cc0:cc1]
        if colors.ndim == 2:
            colors = np.repeat(colors[:, :, None], 3, axis=2)
        parts = [np.flipud(colors).astype(np.uint8), np.flipud(np.asarray(source.counts)[iy0:iy1, cc0:cc1] > 0)]
        fills = [0, False]
    parts.append(np.ones(parts[1].shape, dtype=bool))
    fills.append(False)
    if (rr0, rr1, cc0, cc1) == (r0, r1, c0, c1):
        return tuple(parts)
    embedded = []
    for part, fill in zip(parts, fills, strict=True):
        full = np.full((r1 - r0, c1 - c0, *part.shape[2:]), fill, dtype=part.dtype)
        full[rr0 - r0:rr1 - r0, cc0 - c0:cc1 - c0] = part
        embedded.append(full)
    return tuple(embedded)


def _pooled_window(source: MapSource, factor: int, r0: int, r1: int, c0: int, c1: int
                   ) -> tuple[np.ndarray, ...]:
    """Rows [r0, r1), columns [c0, c1) of the map (north up, multiples of ``factor``) pooled by ``factor``;
    from a pyramid, read from its level for ``factor`` (the same pixels, never the whole map)."""
    if isinstance(source, TilePyramid):
        if factor > 1:
            return source.pooled_window(factor, r0, r1, c0, c1)
        source = source.base()
    return _pool(source, _window(source, r0, r1, c0, c1), factor)


def _pool(source: OccupancyGrid | TextureMap, window: tuple[np.ndarray, ...], factor: int
          ) -> tuple[np.ndarray, ...]:
    if isinstance(source, OccupancyGrid):
        values, known, inside = window
        return pool_occupancy(values, known, inside, factor)
    colors, seen, inside = window
    pooled_colors, pooled_seen = pool_texture(colors, seen, factor)
    _, _, pooled_inside = pool_occupancy(np.zeros(seen.shape), seen, inside, factor)
    return pooled_colors, pooled_seen, pooled_inside


def _shade(source: MapSource, pooled: tuple[np.ndarray, ...]) -> np.ndarray:
    """RGBA uint8 pixels of pooled values."""
    if _layer(source, None) == "occupancy":
        log_odds, known, inside = pooled
        with np.errstate(over="ignore"):  # unknown blocks hold -inf
            probability = 1.0 / (1.0 + np.exp(-log_odds.astype(np.float64)))
        gray = occupancy_gray(probability, known)
        rgb = np.repeat(gray[:, :, None], 3, axis=2)
        alpha = inside
    else:
        rgb, seen, _ = pooled
        alpha = seen
    return np.dstack([rgb, np.where(alpha, np.uint8(255), np.uint8(0))]).astype(np.uint8)


def _simple_tile(source: MapSource, z: int, x: int, y: int) -> np.ndarray:
    scheme = TileScheme.for_map(source)
    scheme.check(z, x, y)
    f = scheme.cells_per_pixel(z)
    span = TILE_SIZE * f
    return _shade(source, _pooled_window(source, f, y * span, (y + 1) * span, x * span, (x + 1) * span))


def _web_mercator_tile(source: MapSource, georef: Georeference | None, z: int, x: int, y: int) -> np.ndarray:
    scheme = WebMercatorScheme.for_map(source, georef)
    assert georef is not None  # for_map raises ConfigError without a geo origin
    scheme.check(z, x, y)
    pixel_m = scheme.tile_m(z) / TILE_SIZE
    offsets = (np.arange(TILE_SIZE) + 0.5) * pixel_m
    mx, my = np.meshgrid(-WEB_MERCATOR_HALF_WORLD_M + x * scheme.tile_m(z) + offsets,
                         WEB_MERCATOR_HALF_WORLD_M - y * scheme.tile_m(z) - offsets)
    map_x, map_y = georef.web_mercator_to_map(mx, my)
    h, w = _shape(source)
    with np.errstate(invalid="ignore", over="ignore"):
        col_f = np.floor((map_x - source.origin_x_m) / source.resolution_m)
        row_f = h - 1 - np.floor((map_y - source.origin_y_m) / source.resolution_m)
    # Far from the UTM zone (low zooms) the projection is meaningless: keep pixels near the map only.
    near = np.isfinite(col_f) & np.isfinite(row_f) & (np.abs(col_f) < 4 * (w + h)) & (np.abs(row_f) < 4 * (w + h))
    rgba = np.zeros((TILE_SIZE, TILE_SIZE, 4), dtype=np.uint8)
    if not near.any():
        return rgba
    col = np.where(near, col_f, -1).astype(np.int64)
    row = np.where(near, row_f, -1).astype(np.int64)
    # Pool by the largest power of two not above the ground pixel size (in cells), at most the
    # simple scheme's zoom-0 factor, blocks aligned with the simple scheme's; then pick the block
    # under each pixel. The pooled window covers only the map.
    simple = TileScheme.for_map(source)
    cells_per_pixel = scheme.ground_m(pixel_m) / source.resolution_m
    f = min(2 ** max(0, math.floor(math.log2(max(cells_per_pixel, 1.0)))), simple.cells_per_pixel(0))
    r0 = max(math.floor(row[near].min() / f) * f, 0)
    c0 = max(math.floor(col[near].min() / f) * f, 0)
    r1 = min((math.floor(row[near].max() / f) + 1) * f, math.ceil(h / f) * f)
    c1 = min((math.floor(col[near].max() / f) + 1) * f, math.ceil(w / f) * f)
    hit = near & (row >= r0) & (row < r1) & (col >= c0) & (col < c1)
    if r1 > r0 and c1 > c0 and hit.any():
        pooled = _shade(source, _pooled_window(source, f, r0, r1, c0, c1))
        rgba[hit] = pooled[(row[hit] - r0) // f, (col[hit] - c0) // f]
    return rgba
