"""Polygons rasterised into a grid mask: the cells a scan looked across (:func:`fill_polygons`).

The rule is OpenCV's ``fillPoly`` with 8-connected edges and sub-cell vertices (it was used here
before, and a polygon inside the grid gets the very same cells): a vertex is in fixed point, ``shift``
fraction bits of a cell; its row is rounded to the nearest cell, and its column is kept with 16
fraction bits. A row's cells between each pair of edge crossings (even-odd, crossings in order)
are set, from the first cell at or right of the left crossing to the last at or left of the
right one; each edge's 8-connected line (Bresenham, drawn left to right between the rounded
vertices) is set too, so that a thin polygon still marks the cells along its outline.

Unlike OpenCV, a polygon that leaves the grid is not clipped first: its lines are walked in full
and only the cells inside the grid are set, so no cell outside the polygon is ever marked (OpenCV's
clipping can mark border cells that the polygon does not cover, and bends clipped lines).
Numba only: the back end needs no OpenCV (about 15 MB resident).
"""

from __future__ import annotations

import numba as nb
import numpy as np

XY_SHIFT = 16  # fraction bits of an edge's column while it is walked down the rows


@nb.njit(cache=True, nogil=True)
def _truncated_division(a: int, b: int) -> int:
    """``a / b`` rounded toward zero (C's integer division; Python's ``//`` rounds down)."""
    q = abs(a) // abs(b)
    return q if (a >= 0) == (b >= 0) else -q


@nb.njit(cache=True, nogil=True)
def _line(mask, x1, y1, x2, y2):
    """Set the cells of the 8-connected line between cells (x1, y1) and (x2, y2) that lie in ``mask``
    (walked from its left end)."""
    rows, cols = mask.shape
    dx = x2 - x1
    dy = y2 - y1
    if dx < 0:
        dx, dy, x1, y1 = -dx, -dy, x2, y2
    step_y = 1
    if dy < 0:
        dy, step_y = -dy, -1
    # a cell along the major axis each step, and one along the minor axis when the error runs out
    steep = dy > dx
    major, minor = (dy, dx) if steep else (dx, dy)
    major_x, major_y, minor_x, minor_y = (0, step_y, 1, 0) if steep else (1, 0, 0, step_y)
    x, y = x1, y1
    err = major - 2 * minor
    for _ in range(major + 1):
        if 0 <= y < rows and 0 <= x < cols:
            mask[y, x] = 1
        if err < 0:
            err += 2 * major
            x += minor_x
            y += minor_y
        err -= 2 * minor
        x += major_x
        y += major_y


@nb.njit(cache=True, nogil=True)
def _fill_one(mask, vx, vy, shift):
    """Set the cells of one polygon (vertices ``vx``, ``vy``: cell coordinates with ``shift``
    fraction bits; cell (0, 0)'s centre at 0)."""
    rows, cols = mask.shape
    n = vx.shape[0]
    half = (1 << shift) >> 1
    edge_y0 = np.empty(n, np.int64)  # first row
    edge_y1 = np.empty(n, np.int64)  # the row after its last
    edge_x = np.empty(n, np.int64)  # column at edge_y0 (XY_SHIFT fraction bits)
    edge_dx = np.empty(n, np.int64)  # column change per row
    n_edges = 0
    rounding = np.int64(1) << (XY_SHIFT - 1)
    x0 = np.int64(vx[n - 1]) << (XY_SHIFT - shift)
    y0 = (np.int64(vy[n - 1]) + half) >> shift
    for i in range(n):
        x1 = np.int64(vx[i]) << (XY_SHIFT - shift)
        y1 = (np.int64(vy[i]) + half) >> shift
        _line(mask, (x0 + rounding) >> XY_SHIFT, y0, (x1 + rounding) >> XY_SHIFT, y1)
        if y0 != y1:
            edge_dx[n_edges] = _truncated_division(x1 - x0, y1 - y0)
            if y0 < y1:
                edge_y0[n_edges], edge_y1[n_edges], edge_x[n_edges] = y0, y1, x0
            else:
                edge_y0[n_edges], edge_y1[n_edges], edge_x[n_edges] = y1, y0, x1
            n_edges += 1
        x0, y0 = x1, y1
    if n_edges < 2:
        return
    order = np.argsort(edge_y0[:n_edges], kind="mergesort")
    active = np.empty(n_edges, np.int64)  # the edges crossing the row, by their crossing's column
    crossing = np.empty(n_edges, np.int64)  # edge k's column on the row (XY_SHIFT fraction bits)
    n_active = 0
    next_edge = 0
    for y in range(edge_y0[order[0]], min(edge_y1[:n_edges].max(), rows)):
        kept = 0
        for a in range(n_active):  # edges end before their last row
            k = active[a]
            if edge_y1[k] != y:
                crossing[k] += edge_dx[k]
                active[kept] = k
                kept += 1
        n_active = kept
        while next_edge < n_edges and edge_y0[order[next_edge]] == y:
            k = order[next_edge]
            crossing[k] = edge_x[k]
            active[n_active] = k
            n_active += 1
            next_edge += 1
        for a in range(1, n_active):  # insertion sort: the order changes little from row to row
            k = active[a]
            b = a - 1
            while b >= 0 and crossing[active[b]] > crossing[k]:
                active[b + 1] = active[b]
                b -= 1
            active[b + 1] = k
        if y < 0:
            continue
        for a in range(0, n_active - 1, 2):
            first = (crossing[active[a]] + (np.int64(1) << XY_SHIFT) - 1) >> XY_SHIFT  # rounded up
            last = crossing[active[a + 1]] >> XY_SHIFT  # rounded down
            for x in range(max(first, 0), min(last, cols - 1) + 1):
                mask[y, x] = 1


@nb.njit(cache=True, nogil=True)
def fill_polygons(mask, vx, vy, starts, shift):
    """Set (to 1) the cells of ``mask`` (rows, cols) uint8 that the polygons cover. Polygon ``p`` has
    vertices ``vx[starts[p]:starts[p + 1]]``, ``vy[...]`` (int64): cell coordinates with ``shift``
    fraction bits, cell (0, 0)'s centre at (0, 0). See the module docstring for the rule."""
    for p in range(starts.shape[0] - 1):
        if starts[p + 1] > starts[p]:
            _fill_one(mask, vx[starts[p]:starts[p + 1]], vy[starts[p]:starts[p + 1]], shift)
