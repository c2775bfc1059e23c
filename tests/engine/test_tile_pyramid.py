"""Tiles cut from a tile pyramid file (read by window) are the tiles of the map held in memory, pixel for
pixel, at every zoom and in both schemes; the file reads back with np.load."""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from slam_engine.errors import TileOutOfRangeError
from slam_engine.model.result import OccupancyGrid, TextureMap
from slam_engine.products import GeoOrigin, Georeference, TileScheme, WebMercatorScheme, render_tile
from slam_engine.products.tile_pyramid import TilePyramid, level_count, open_map, write_tile_pyramid


def grid_of(h: int, w: int, seed: int = 5, dtype=np.float32) -> OccupancyGrid:
    rng = np.random.default_rng(seed)
    log_odds = rng.choice(np.array([-5.0, -0.4, 0.0, 0.0, 0.9, 5.0], dtype=dtype), size=(h, w))
    return OccupancyGrid(log_odds, 0.05, -3.0, -7.0)


def texture_of(h: int, w: int, gray: bool, seed: int = 6) -> TextureMap:
    rng = np.random.default_rng(seed)
    colors = rng.integers(0, 256, size=(h, w) if gray else (h, w, 3), dtype=np.uint8)
    counts = rng.choice(np.array([0, 0, 1, 7], dtype=np.uint16), size=(h, w))
    return TextureMap(colors, counts, 0.05, -3.0, -7.0)


def pixels(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)))


@pytest.mark.parametrize("shape", [(300, 700), (1100, 513), (257, 256), (100, 90)])
def test_every_simple_tile_from_the_pyramid_is_the_tile_of_the_grid(tmp_path: Path, shape) -> None:
    grid = grid_of(*shape)
    pyramid = TilePyramid.open(write_tile_pyramid(grid, tmp_path / "grid.npz"))
    assert pyramid is not None and pyramid.shape == shape and pyramid.levels == level_count(shape)
    scheme = TileScheme.for_map(grid)
    assert TileScheme.for_map(pyramid) == scheme
    for z in range(scheme.max_zoom + 1):
        nx, ny = scheme.tile_counts(z)
        for x in range(nx):
            for y in range(ny):
                np.testing.assert_array_equal(pixels(render_tile(pyramid, z, x, y)),
                                              pixels(render_tile(grid, z, x, y)), err_msg=f"{z}/{x}/{y}")
    with pytest.raises(TileOutOfRangeError):
        render_tile(pyramid, scheme.max_zoom + 1, 0, 0)
    with np.load(tmp_path / "grid.npz") as z:  # the map itself, as before, for any reader
        np.testing.assert_array_equal(z["log_odds"], grid.log_odds)
        assert float(z["resolution_m"]) == 0.05


@pytest.mark.parametrize("gray", [False, True])
def test_texture_tiles_from_the_pyramid_are_the_textures_tiles(tmp_path: Path, gray: bool) -> None:
    texture = texture_of(700, 1030, gray)
    pyramid = TilePyramid.open(write_tile_pyramid(texture, tmp_path / "texture.npz"))
    assert pyramid is not None and pyramid.layer == "texture"
    scheme = TileScheme.for_map(texture)
    for z in range(scheme.max_zoom + 1):
        nx, ny = scheme.tile_counts(z)
        for x in range(nx):
            for y in range(ny):
                np.testing.assert_array_equal(pixels(render_tile(pyramid, z, x, y, layer="texture")),
                                              pixels(render_tile(texture, z, x, y, layer="texture")))


def test_web_mercator_tiles_from_the_pyramid_are_the_grids(tmp_path: Path) -> None:
    grid = grid_of(900, 1300)
    pyramid = TilePyramid.open(write_tile_pyramid(grid, tmp_path / "grid.npz"))
    georef = Georeference.utm(GeoOrigin(48.137154, 11.576124, 30.0), np.zeros(3))
    scheme = WebMercatorScheme.for_map(grid, georef)
    for z in range(scheme.max_zoom - 6, scheme.max_zoom + 1):
        x0, x1, y0, y1 = scheme.tile_range(z)
        for x, y in {(x0, y0), (x1, y1), ((x0 + x1) // 2, (y0 + y1) // 2)}:
            np.testing.assert_array_equal(
                pixels(render_tile(pyramid, z, x, y, scheme="webmercator", georef=georef)),
                pixels(render_tile(grid, z, x, y, scheme="webmercator", georef=georef)), err_msg=f"{z}/{x}/{y}")


def test_a_map_file_without_levels_converts_from_its_mapping(tmp_path: Path) -> None:
    grid = grid_of(600, 1000)
    np.savez(tmp_path / "old.npz", log_odds=grid.log_odds, resolution_m=0.05, origin_x_m=-3.0, origin_y_m=-7.0)
    assert TilePyramid.open(tmp_path / "old.npz") is None
    mapped = open_map(tmp_path / "old.npz")
    assert isinstance(mapped, OccupancyGrid) and isinstance(mapped.log_odds, np.memmap)
    pyramid = TilePyramid.open(write_tile_pyramid(mapped, tmp_path / "new.npz"))
    assert pyramid is not None
    for z, x, y in [(0, 0, 0), (1, 1, 0), (2, 3, 2)]:
        np.testing.assert_array_equal(pixels(render_tile(pyramid, z, x, y)), pixels(render_tile(grid, z, x, y)))


def test_a_single_wall_cell_survives_every_level(tmp_path: Path) -> None:
    """A 3000 x 3000 grid of one wall cell: zoom 0 (12 x 12 cells a pixel) and native zoom both show it."""
    h = w = 3000
    path = tmp_path / "huge.npz"
    grid = OccupancyGrid(np.lib.format.open_memmap(tmp_path / "huge_log_odds.npy", mode="w+", dtype=np.float32,
                                                   shape=(h, w)), 0.05, 0.0, 0.0)
    grid.log_odds[h - 1, 0] = 5.0  # one wall cell at the top-left
    write_tile_pyramid(grid, path)
    pyramid = TilePyramid.open(path)
    assert pyramid is not None and pyramid.levels == math.ceil(math.log2(h / 256)) == 4
    top = pixels(render_tile(pyramid, 0, 0, 0))
    assert top[0, 0, 0] < 10 and top[0, 0, 3] == 255 and top[0, 1, 0] == 205
    native = pixels(render_tile(pyramid, 4, 0, 0))
    assert native[0, 0, 0] < 10 and native[1, 1, 0] == 205
