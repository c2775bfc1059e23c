"""Grid and texture to images (north up), trajectory overlays, and block pooling for zoomed-out views.

Image convention: row 0 is the map's top (largest y), column 0 its left (smallest x), so the
image of a grid is its ``log_odds`` flipped upside down; cell (ix, iy) is pixel (ix, H - 1 - iy).
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw

from slam_engine.model.result import OccupancyGrid, TextureMap, Trajectory

OCCUPIED_THRESHOLD = 0.65  # probability above which a cell counts as occupied (also map.yaml)
FREE_THRESHOLD = 0.196  # probability below which a cell counts as free (also map.yaml)
UNKNOWN_GRAY = 205  # grey level of never-observed cells (the ROS map_saver convention)
ROS_OCCUPIED, ROS_FREE, ROS_UNKNOWN = 0, 254, 205  # trinary ROS map values (map_saver)
TRAJECTORY_RGB = (220, 30, 30)
REFERENCE_RGB = (30, 90, 230)  # dead reckoning or ground truth
START_RGB = (20, 160, 40)
# zlib level of the PNG products: level 1 encodes a map 2-3x faster than Pillow's default 6, for files
# within about 20 % of its size (maps are mostly flat areas that any level compresses well).
PNG_COMPRESS_LEVEL = 1


def occupancy_north_up(grid: OccupancyGrid) -> tuple[np.ndarray, np.ndarray]:
    """(probability, known) arrays, each (H, W), with row 0 at the top (north up)."""
    return np.flipud(grid.probability()), np.flipud(grid.known())


def occupancy_gray(probability: np.ndarray, known: np.ndarray) -> np.ndarray:
    """uint8 grey image: known cells shaded white (free, p = 0) to black (occupied, p = 1),
    unknown cells :data:`UNKNOWN_GRAY`."""
    shade = np.rint(255.0 * (1.0 - np.clip(probability, 0.0, 1.0))).astype(np.uint8)
    return np.where(known, shade, np.uint8(UNKNOWN_GRAY))


_BAND_ROWS = 64  # rasters are computed this many rows at a time: float64 temporaries stay small


@dataclass(frozen=True)
class OccupancyRasters:
    """North-up rasters of one grid, computed once for every product that shows it:
    ``gray`` (H, W) uint8 as :func:`occupancy_gray`; ``trinary`` (H, W) uint8, the ROS map's
    values (:data:`ROS_OCCUPIED` where the probability as float32 is above
    :data:`OCCUPIED_THRESHOLD`, :data:`ROS_FREE` below :data:`FREE_THRESHOLD`, else
    :data:`ROS_UNKNOWN`); and the numbers of known, occupied and free cells (float64
    probability, for run.json). The GeoTIFF's float32 probability raster is written strip by strip
    instead (:func:`probability_band`): a float32 raster is 4 bytes a cell."""

    gray: np.ndarray
    trinary: np.ndarray
    known_cells: int
    occupied_cells: int
    free_cells: int


def north_up_log_odds(grid: OccupancyGrid, r0: int, r1: int) -> np.ndarray:
    """North-up rows ``r0..r1`` of the grid's log-odds (a view)."""
    h = grid.shape[0]
    return grid.log_odds[h - r1:h - r0][::-1]


def probability_band(grid: OccupancyGrid, r0: int, r1: int) -> np.ndarray:
    """North-up rows ``r0..r1`` of the GeoTIFF's values: float32 probability, -1 where unknown
    (the same values as from the whole-grid :func:`occupancy_north_up`), computed :data:`_BAND_ROWS`
    rows at a time (the float64 temporaries of a 256-row strip took 40 MB on the corridor's map)."""
    out = np.empty((r1 - r0, grid.shape[1]), np.float32)
    for a in range(r0, r1, _BAND_ROWS):
        log_odds = north_up_log_odds(grid, a, min(r1, a + _BAND_ROWS))
        p = 1.0 / (1.0 + np.exp(-log_odds.astype(np.float64)))
        out[a - r0: a - r0 + len(log_odds)] = np.where(log_odds != 0.0, p, -1.0)
    return out


def occupancy_rasters(grid: OccupancyGrid) -> OccupancyRasters:
    """Every north-up raster of ``grid`` in one pass, band by band (the same values as computing
    each from :func:`occupancy_north_up`, without its full-size float64 temporaries)."""
    h, w = grid.shape
    gray = np.empty((h, w), np.uint8)
    trinary = np.empty((h, w), np.uint8)
    known_cells = occupied_cells = free_cells = 0
    for r0 in range(0, h, _BAND_ROWS):
        r1 = min(h, r0 + _BAND_ROWS)
        log_odds = north_up_log_odds(grid, r0, r1)
        known = log_odds != 0.0
        p = 1.0 / (1.0 + np.exp(-log_odds.astype(np.float64)))
        gray[r0:r1] = occupancy_gray(p, known)
        # the ROS map compares the GeoTIFF's float32 values (stored log-odds are multiples of 0.01,
        # none near a threshold: the same cells as float64)
        p32 = np.where(known, p, -1.0).astype(np.float32)
        band = np.full(p32.shape, ROS_UNKNOWN, np.uint8)
        band[known & (p32 > OCCUPIED_THRESHOLD)] = ROS_OCCUPIED
        band[known & (p32 < FREE_THRESHOLD)] = ROS_FREE
        trinary[r0:r1] = band
        known_cells += int(np.count_nonzero(known))
        occupied_cells += int(np.count_nonzero(known & (p > OCCUPIED_THRESHOLD)))
        free_cells += int(np.count_nonzero(known & (p < FREE_THRESHOLD)))
    return OccupancyRasters(gray, trinary, known_cells, occupied_cells, free_cells)


def occupancy_image(grid: OccupancyGrid) -> Image.Image:
    """The grid as a north-up greyscale ("L") image, one pixel per cell."""
    return Image.fromarray(occupancy_gray(*occupancy_north_up(grid)))


def texture_north_up(texture: TextureMap) -> tuple[np.ndarray, np.ndarray]:
    """(colors (H, W, 3) uint8, seen (H, W) bool), north up; grayscale textures become RGB."""
    colors = np.asarray(texture.colors)
    if colors.ndim == 2:
        colors = np.repeat(colors[:, :, None], 3, axis=2)
    return np.flipud(colors.astype(np.uint8)), np.flipud(np.asarray(texture.counts) > 0)


def texture_image(texture: TextureMap) -> Image.Image:
    """The texture as a north-up RGBA image; never-seen cells are transparent."""
    colors, seen = texture_north_up(texture)
    alpha = np.where(seen, np.uint8(255), np.uint8(0))
    return Image.fromarray(np.dstack([colors, alpha]))


def map_pixels(grid: OccupancyGrid, poses: np.ndarray) -> np.ndarray:
    """(N, 2) image coordinates (column, row; continuous, pixel centres at +0.5) of map-frame poses."""
    col = (poses[:, 0] - grid.origin_x_m) / grid.resolution_m
    row = grid.shape[0] - (poses[:, 1] - grid.origin_y_m) / grid.resolution_m
    return np.column_stack([col, row])


def occupancy_with_trajectories(grid: OccupancyGrid, trajectory: Trajectory,
                                reference: Trajectory | None = None, gray: np.ndarray | None = None) -> Image.Image:
    """RGB map image with a reference track (dead reckoning or ground truth, blue), the SLAM
    trajectory (red) on top and a green start dot. ``gray``: the grid's grey image when already made
    (:class:`OccupancyRasters`)."""
    image = (occupancy_image(grid) if gray is None else Image.fromarray(gray)).convert("RGB")
    _draw_trajectories(ImageDraw.Draw(image), grid, trajectory, reference, (REFERENCE_RGB, TRAJECTORY_RGB, START_RGB))
    return image


def _draw_trajectories(draw: ImageDraw.ImageDraw, grid: OccupancyGrid, trajectory: Trajectory,
                       reference: Trajectory | None, inks: tuple) -> None:
    """The reference track, the trajectory and the start dot with ``inks`` (reference, trajectory, start)."""
    for traj, ink in ((reference, inks[0]), (trajectory, inks[1])):
        if traj is not None and len(traj) > 1:
            draw.line([tuple(p) for p in map_pixels(grid, traj.poses)], fill=ink, width=1)
    if len(trajectory):
        c, r = map_pixels(grid, trajectory.poses[:1])[0]
        draw.ellipse([c - 2, r - 2, c + 2, r + 2], fill=inks[2])


def write_occupancy_with_trajectories_png(path, grid: OccupancyGrid, trajectory: Trajectory,
                                          reference: Trajectory | None, gray: np.ndarray) -> None:
    """Write :func:`occupancy_with_trajectories` (the same pixels) as an RGB PNG without the RGB image
    in memory: the tracks are drawn once into a one-byte-a-pixel mask of which ink goes where, and
    the PNG is encoded a band of rows at a time (zlib level :data:`PNG_COMPRESS_LEVEL`)."""
    mask = Image.new("L", (gray.shape[1], gray.shape[0]), 0)
    _draw_trajectories(ImageDraw.Draw(mask), grid, trajectory, reference, (1, 2, 3))
    inks = np.array([(0, 0, 0), REFERENCE_RGB, TRAJECTORY_RGB, START_RGB], np.uint8)
    height, width = gray.shape

    def rows():
        for r0 in range(0, height, _BAND_ROWS):
            band = np.repeat(gray[r0:r0 + _BAND_ROWS, :, None], 3, axis=2)
            # the mask's band alone: the whole mask as an array took two more copies of it at once
            drawn = np.asarray(mask.crop((0, r0, width, min(r0 + _BAND_ROWS, height))))
            marked = drawn > 0
            band[marked] = inks[drawn[marked]]
            yield band

    write_png_rows(path, width, height, rows())


def write_png_rows(path, width: int, height: int, bands) -> None:
    """Write an 8-bit RGB PNG from ``bands``: (rows, width, 3) uint8 arrays, top to bottom, ``height``
    rows in all; each row unfiltered, the stream compressed as it is written."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    compressor = zlib.compressobj(PNG_COMPRESS_LEVEL)
    written = 0
    with open(path, "wb") as out:
        out.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)))
        for band in bands:
            band = np.ascontiguousarray(band, np.uint8).reshape(band.shape[0], width * 3)
            filtered = np.empty((band.shape[0], width * 3 + 1), np.uint8)
            filtered[:, 0] = 0  # filter type None
            filtered[:, 1:] = band
            written += band.shape[0]
            data = compressor.compress(filtered.tobytes())
            if data:
                out.write(chunk(b"IDAT", data))
        out.write(chunk(b"IDAT", compressor.flush()) + chunk(b"IEND", b""))
    if written != height:
        raise ValueError(f"write_png_rows: {written} rows given for a {height}-row image")


def png_bytes(image: Image.Image) -> bytes:
    """``image`` encoded as a PNG file, in memory."""
    buffer = io.BytesIO()
    image.save(buffer, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
    return buffer.getvalue()


def _pad_to_blocks(array: np.ndarray, factor: int, fill) -> np.ndarray:
    """Pad rows and columns at the bottom/right up to multiples of ``factor``."""
    pad_r = -array.shape[0] % factor
    pad_c = -array.shape[1] % factor
    if not (pad_r or pad_c):
        return array
    widths = [(0, pad_r), (0, pad_c)] + [(0, 0)] * (array.ndim - 2)
    return np.pad(array, widths, constant_values=fill)


def _block_reduce(array: np.ndarray, factor: int, reducer: np.ufunc) -> np.ndarray:
    """Reduce (H, W, ...) over f x f blocks (H, W multiples of f): columns first, then rows."""
    h, w = array.shape[:2]
    rest = array.shape[2:]
    by_columns = reducer.reduce(array.reshape(h, w // factor, factor, *rest), axis=2)
    return reducer.reduce(by_columns.reshape(h // factor, factor, w // factor, *rest), axis=1)


def pool_occupancy(values: np.ndarray, known: np.ndarray, inside: np.ndarray,
                   factor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reduce f x f blocks to one pixel, keeping obstacles visible: the block's value (log-odds or
    probability: any increasing function of occupancy) is the largest among its known cells;
    known / inside = any cell known / inside the map."""
    if factor == 1:
        return values, known, inside
    p = _block_reduce(_pad_to_blocks(np.where(known, values, -np.inf), factor, -np.inf), factor, np.maximum)
    k = _block_reduce(_pad_to_blocks(known, factor, False), factor, np.logical_or)
    i = _block_reduce(_pad_to_blocks(inside, factor, False), factor, np.logical_or)
    return p, k, i


def pool_texture(colors: np.ndarray, seen: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Reduce f x f blocks to the mean colour of their seen cells; seen = any seen."""
    if factor == 1:
        return colors, seen
    s = _pad_to_blocks(seen, factor, False)
    c = _pad_to_blocks(colors, factor, 0) * s[..., None]
    n = _block_reduce(s.astype(np.int64), factor, np.add)
    total = _block_reduce(c.astype(np.int64), factor, np.add)
    mean = total / np.maximum(n, 1)[..., None]
    return np.rint(mean).astype(np.uint8), n > 0
