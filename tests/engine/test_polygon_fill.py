"""The back end's polygon rasteriser: OpenCV's fillPoly cells inside the grid, no clipping artefacts outside."""

from __future__ import annotations

import cv2
import numpy as np

from slam_engine.backend.polygon_fill import fill_polygons

SHIFT = 4  # 1/16 cell, as observed_mask uses


def filled(shape: tuple[int, int], *polygons: np.ndarray) -> np.ndarray:
    mask = np.zeros(shape, np.uint8)
    vertices = np.concatenate(polygons).astype(np.int64)
    starts = np.concatenate([[0], np.cumsum([len(p) for p in polygons])]).astype(np.int64)
    fill_polygons(mask, np.ascontiguousarray(vertices[:, 0]), np.ascontiguousarray(vertices[:, 1]), starts, SHIFT)
    return mask


def random_polygon(rng: np.random.Generator, rows: int, cols: int) -> np.ndarray:
    """Vertices (1/16 cell) whose rounded cells lie in the grid: scan-like fans, any polygons, and
    vertices on the lattice (ties between crossings)."""
    n = int(rng.integers(1, 40))
    high = np.array([cols - 0.55, rows - 0.55])
    kind = int(rng.integers(3))
    if kind == 0:
        origin = rng.uniform(0.0, high)
        bearing = np.sort(rng.uniform(-np.pi, np.pi, n))
        reach = rng.uniform(0.0, 50.0, n)
        ends = origin + reach[:, None] * np.column_stack([np.cos(bearing), np.sin(bearing)])
        ring = np.vstack([origin, np.clip(ends, -0.45, high)])
    elif kind == 1:
        ring = rng.uniform(-0.45, high, (n, 2))
    else:
        ring = np.clip(rng.integers(0, [cols, rows], (n, 2)) + rng.choice([0.0, 0.5, 1 / 16], (n, 2)), -0.45, high)
    return np.round(ring * (1 << SHIFT)).astype(np.int32)


def test_polygons_inside_the_grid_get_opencvs_cells() -> None:
    rng = np.random.default_rng(7)
    for _ in range(3000):
        rows, cols = (int(v) for v in rng.integers(1, 50, 2))
        polygon = random_polygon(rng, rows, cols)
        expected = np.zeros((rows, cols), np.uint8)
        cv2.fillPoly(expected, [polygon], 1, lineType=cv2.LINE_8, shift=SHIFT)
        assert np.array_equal(filled((rows, cols), polygon), expected), polygon.tolist()


def test_several_polygons_in_one_call_mark_their_union() -> None:
    rng = np.random.default_rng(3)
    polygons = [random_polygon(rng, 30, 40) for _ in range(5)]
    union = np.zeros((30, 40), np.uint8)
    for polygon in polygons:
        union |= filled((30, 40), polygon)
    assert np.array_equal(filled((30, 40), *polygons), union)
    assert union.any()


def test_a_polygon_leaving_the_grid_marks_what_it_covers_there() -> None:
    """A grid's cells are the same whether the polygon fits in it or not: filling a window equals
    cropping the fill of a grid around the whole polygon (OpenCV's clipping can mark border cells
    that the polygon does not cover)."""
    rng = np.random.default_rng(11)
    pad = 40
    for _ in range(500):
        rows, cols = (int(v) for v in rng.integers(2, 30, 2))
        n = int(rng.integers(3, 20))
        ring = rng.uniform(-12.0, [cols + 12.0, rows + 12.0], (n, 2))
        polygon = np.round(ring * (1 << SHIFT)).astype(np.int64)
        whole = filled((rows + 2 * pad, cols + 2 * pad), polygon + (pad << SHIFT))
        assert np.array_equal(filled((rows, cols), polygon), whole[pad:pad + rows, pad:pad + cols])
    # a wedge whose tip lies left of the grid: column 0 is marked between its edges (y 6.7-13.3)
    wedge = np.array([[-10.0, 10.0], [5.0, 5.0], [5.0, 15.0]]) * (1 << SHIFT)
    mask = filled((20, 8), wedge.astype(np.int64))
    assert mask[:, 0].nonzero()[0].tolist() == list(range(7, 14))
    assert mask[10, :6].all() and not mask[10, 6:].any() and not mask[:5].any() and not mask[16:].any()
