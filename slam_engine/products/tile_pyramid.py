"""A map as a tile pyramid on disk, read by window: what tiles are cut from without loading the map.

The file is an uncompressed ``.npz`` (``np.load`` reads it as usual) holding the map itself (an
occupancy grid's ``log_odds``, or a texture's ``colors`` and ``counts``, with ``resolution_m``,
``origin_x_m``, ``origin_y_m``) and its pooled levels 1 .. the tiles' zoom-0 level, each level halving
the one below, north up (row 0 = the map's top), padded at the bottom and right as tiles are:

* occupancy, ``level_k``: per block of 2^k x 2^k cells the largest log-odds among its known cells,
  ``-inf`` where none is known (the value tiles show when zoomed out: obstacles stay visible);
* texture, ``sum_k`` (3 channels) and ``seen_k``: the colour sum and the number of seen cells per block
  (the tile's pixel is their mean).

:meth:`TilePyramid.open` memory-maps every array on demand and copies out only the window asked for,
so a tile of a 250 MB grid reads at most 256 x 256 cells of one level. Levels are built in bands of
rows: writing costs about a third of the map's size on top of the map."""

from __future__ import annotations

import math
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from slam_engine.model.result import OccupancyGrid, TextureMap
from slam_engine.products.files import atomic_path

TILE_SIZE = 256
PYRAMID_VERSION = 1
BAND_ROWS = 256  # the map is read, pooled and written this many rows at a time (an even number)
_SUM_UINT32_LEVELS = 12  # colour sums of 4^k cells fit uint32 up to this level (255 * 4^12 < 2^32)


def level_count(shape: tuple[int, int]) -> int:
    """Pooled levels a map of ``shape`` cells needs: until one tile holds it whole (the tiles' zoom 0)."""
    return max(0, math.ceil(math.log2(max(shape[0], shape[1], 1) / TILE_SIZE)))


def _pad_reduce(array: np.ndarray, fill, reducer: np.ufunc) -> np.ndarray:
    """2 x 2 blocks of (H, W, ...) reduced to one cell, padding the bottom/right with ``fill``."""
    pad = [(0, array.shape[0] % 2), (0, array.shape[1] % 2)] + [(0, 0)] * (array.ndim - 2)
    if pad[0][1] or pad[1][1]:
        array = np.pad(array, pad, constant_values=fill)
    return reducer(reducer(array[0::2, 0::2], array[0::2, 1::2]), reducer(array[1::2, 0::2], array[1::2, 1::2]))


def _rows(array: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """Rows [lo, hi) of ``array`` as an array of their own; of a memory-mapped array, read through a
    mapping of those rows alone (dropped at once), so reading a mapped map band by band never holds it."""
    if isinstance(array, np.memmap) and array.filename and array.flags.c_contiguous and hi > lo:
        part = np.memmap(array.filename, dtype=array.dtype, mode="r", offset=array.offset + lo * array.strides[0],
                         shape=(hi - lo, *array.shape[1:]))
        rows = np.array(part)
        del part
        return rows
    return np.asarray(array[lo:hi])


def _occupancy_level_1(log_odds: np.ndarray) -> np.ndarray:
    """Level 1 of a grid (rows bottom-up), pooled BAND_ROWS north-up rows at a time."""
    h = log_odds.shape[0]
    bands = []
    for top in range(0, h, BAND_ROWS):
        rows = np.flipud(_rows(log_odds, max(h - top - BAND_ROWS, 0), h - top))  # north-up [top, top + BAND_ROWS)
        bands.append(_pad_reduce(np.where(rows != 0.0, rows, -np.inf).astype(log_odds.dtype), -np.inf, np.maximum))
    return np.concatenate(bands) if bands else np.zeros((0, 0), log_odds.dtype)


def _texture_level_1(colors: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Level 1 of a texture (rows bottom-up): colour sums of the seen cells and their number."""
    h = counts.shape[0]
    sums, seens = [], []
    for top in range(0, h, BAND_ROWS):
        lo, hi = max(h - top - BAND_ROWS, 0), h - top
        seen = np.flipud(_rows(counts, lo, hi) > 0)
        rgb = np.flipud(_rows(colors, lo, hi))
        if rgb.ndim == 2:
            rgb = np.repeat(rgb[:, :, None], 3, axis=2)
        sums.append(_pad_reduce(rgb.astype(np.uint32) * seen[..., None], 0, np.add))
        seens.append(_pad_reduce(seen.astype(np.uint32), 0, np.add))
    return np.concatenate(sums), np.concatenate(seens)


def write_tile_pyramid(source: OccupancyGrid | TextureMap, path: str | Path) -> Path:
    """Write ``source`` with its pooled levels as a tile pyramid file (atomically); returns the path."""
    meta: dict[str, Any] = {"pyramid_version": np.int64(PYRAMID_VERSION),
                            "resolution_m": np.float64(source.resolution_m),
                            "origin_x_m": np.float64(source.origin_x_m), "origin_y_m": np.float64(source.origin_y_m)}
    arrays: dict[str, Any] = {}
    if isinstance(source, OccupancyGrid):
        shape = source.log_odds.shape
        arrays["log_odds"] = source.log_odds
        levels = level_count(shape)
        if levels:
            level = _occupancy_level_1(source.log_odds)
            arrays["level_1"] = level
            for k in range(2, levels + 1):
                level = _pad_reduce(level, -np.inf, np.maximum)
                arrays[f"level_{k}"] = level
    else:
        counts = source.counts
        shape = counts.shape
        arrays["colors"], arrays["counts"] = source.colors, counts
        levels = level_count(shape)
        if levels:
            sums, seen = _texture_level_1(source.colors, counts)
            arrays["sum_1"], arrays["seen_1"] = sums, seen
            for k in range(2, levels + 1):
                wide = np.uint32 if k <= _SUM_UINT32_LEVELS else np.uint64
                sums = _pad_reduce(sums.astype(wide, copy=False), 0, np.add)
                seen = _pad_reduce(seen, 0, np.add)
                arrays[f"sum_{k}"], arrays[f"seen_{k}"] = sums, seen
    with atomic_path(path) as tmp:
        _write_npz(tmp, {**meta, **arrays})
    return Path(path)


def _write_npz(path: Path, arrays: dict[str, Any]) -> None:
    """An uncompressed .npz as ``np.savez`` writes it, each array written BAND_ROWS rows at a time."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED, allowZip64=True) as archive:
        for name, value in arrays.items():
            array = value if isinstance(value, np.ndarray) else np.asarray(value)
            header = {"descr": np.lib.format.dtype_to_descr(array.dtype), "fortran_order": False,
                      "shape": array.shape}
            with archive.open(f"{name}.npy", "w", force_zip64=True) as out:
                np.lib.format.write_array_header_1_0(out, header)
                if array.ndim == 0:
                    out.write(array.tobytes())
                    continue
                for lo in range(0, array.shape[0], BAND_ROWS):
                    out.write(np.ascontiguousarray(_rows(array, lo, min(lo + BAND_ROWS, array.shape[0]))).tobytes())


def open_map(path: str | Path) -> OccupancyGrid | TextureMap | None:
    """The map in an uncompressed .npz (a pyramid file, or a map file of an earlier version: ``log_odds``
    or ``colors`` and ``counts``, with the placement), its arrays memory-mapped; None when they are
    compressed."""
    with open(path, "rb") as file:
        members = _members(file)
        file.seek(0)
        with np.load(file) as z:
            placement = {name: float(z[name]) for name in ("resolution_m", "origin_x_m", "origin_y_m")}

    def mapped(name: str) -> np.memmap:
        member = members[name]
        return np.memmap(path, dtype=member.dtype, mode="r", offset=member.offset, shape=member.shape,
                         order="F" if member.fortran_order else "C")

    if "log_odds" in members:
        return OccupancyGrid(log_odds=mapped("log_odds"), **placement)
    if "colors" in members and "counts" in members:
        return TextureMap(colors=mapped("colors"), counts=mapped("counts"), **placement)
    return None


@dataclass(frozen=True)
class _Member:
    """Where one array lies in the pyramid file."""

    offset: int
    dtype: np.dtype
    shape: tuple[int, ...]
    fortran_order: bool


def _members(raw: BinaryIO) -> dict[str, _Member]:
    """The arrays of an uncompressed .npz (an open file) and where their data starts (compressed members:
    left out)."""
    found: dict[str, _Member] = {}
    with zipfile.ZipFile(raw) as archive:
        for info in archive.infolist():
            if info.compress_type != zipfile.ZIP_STORED or not info.filename.endswith(".npy"):
                continue
            raw.seek(info.header_offset)
            local = raw.read(30)
            if local[:4] != b"PK\x03\x04":
                continue
            name_len, extra_len = int.from_bytes(local[26:28], "little"), int.from_bytes(local[28:30], "little")
            raw.seek(info.header_offset + 30 + name_len + extra_len)
            version = np.lib.format.read_magic(raw)
            shape, fortran, dtype = (np.lib.format.read_array_header_1_0(raw) if version == (1, 0)
                                     else np.lib.format.read_array_header_2_0(raw))
            found[info.filename[:-4]] = _Member(raw.tell(), dtype, shape, fortran)
    return found


class TilePyramid:
    """A tile pyramid file opened for reading windows (see the module docstring). ``layer`` is
    "occupancy" or "texture"; ``shape`` (rows, cols) and the placement are the map's. The file stays
    open while the object lives, so a file replaced meanwhile (a running job's map) is never mixed in;
    ``version`` names the file's version (device, inode, size, modification time)."""

    def __init__(self, file: BinaryIO, members: dict[str, _Member], resolution_m: float, origin_x_m: float,
                 origin_y_m: float):
        self._file = file
        self._members = members
        stat = os.fstat(file.fileno())
        self.version = (stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns)
        self.layer = "occupancy" if "log_odds" in members else "texture"
        base = members["log_odds" if self.layer == "occupancy" else "counts"]
        self.shape: tuple[int, int] = (int(base.shape[0]), int(base.shape[1]))
        self.resolution_m, self.origin_x_m, self.origin_y_m = resolution_m, origin_x_m, origin_y_m
        self.levels = level_count(self.shape)

    @classmethod
    def open(cls, path: str | Path) -> TilePyramid | None:
        """The pyramid in the file at ``path``; None when the file is a map without levels (written
        by an earlier version: :func:`write_tile_pyramid` makes one from it)."""
        file = open(path, "rb")  # noqa: SIM115 (kept open by the pyramid)
        try:
            members = _members(file)
            file.seek(0)
            with np.load(file) as z:
                if "pyramid_version" not in z.files:
                    file.close()
                    return None
                meta = {name: float(z[name]) for name in ("resolution_m", "origin_x_m", "origin_y_m")}
        except BaseException:
            file.close()
            raise
        return cls(file, members, **meta)

    def close(self) -> None:
        self._file.close()

    def _array(self, name: str) -> np.memmap:
        """A fresh read-only mapping of one array (dropped after use: its pages are not kept mapped)."""
        member = self._members[name]
        return np.memmap(self._file, dtype=member.dtype, mode="r", offset=member.offset, shape=member.shape,
                         order="F" if member.fortran_order else "C")

    def base(self) -> OccupancyGrid | TextureMap:
        """The map itself, its arrays memory-mapped (slice them; never read them whole)."""
        placement = {"resolution_m": self.resolution_m, "origin_x_m": self.origin_x_m,
                     "origin_y_m": self.origin_y_m}
        if self.layer == "occupancy":
            return OccupancyGrid(log_odds=self._array("log_odds"), **placement)
        return TextureMap(colors=self._array("colors"), counts=self._array("counts"), **placement)

    def pooled_window(self, factor: int, r0: int, r1: int, c0: int, c1: int) -> tuple[np.ndarray, ...]:
        """Rows [r0, r1) and columns [c0, c1) of the map (north up, multiples of ``factor`` = 2^k, k >= 1)
        pooled by ``factor``, as :func:`~slam_engine.products.rendering.pool_occupancy` (values, known,
        inside) or :func:`~slam_engine.products.rendering.pool_texture` (colors, seen, inside) would
        give them; outside the map: unknown and not inside."""
        k = int(factor).bit_length() - 1
        if factor != 1 << k or not 1 <= k <= self.levels:
            raise ValueError(f"factor {factor}: a power of two from 2 to {2**self.levels}")
        rows, cols = (r0 // factor, r1 // factor), (c0 // factor, c1 // factor)
        if self.layer == "occupancy":
            values = self._window(f"level_{k}", rows, cols, -np.inf)
            inside = self._inside(f"level_{k}", rows, cols)
            return values, values > -np.inf, inside
        sums = self._window(f"sum_{k}", rows, cols, 0)
        seen = self._window(f"seen_{k}", rows, cols, 0)
        mean = sums / np.maximum(seen, 1)[..., None]
        return np.rint(mean).astype(np.uint8), seen > 0, self._inside(f"seen_{k}", rows, cols)

    def _window(self, name: str, rows: tuple[int, int], cols: tuple[int, int], fill) -> np.ndarray:
        level = self._array(name)
        h, w = level.shape[:2]
        out = np.full((rows[1] - rows[0], cols[1] - cols[0], *level.shape[2:]), fill, dtype=level.dtype)
        rr0, rr1 = max(rows[0], 0), min(rows[1], h)
        cc0, cc1 = max(cols[0], 0), min(cols[1], w)
        if rr1 > rr0 and cc1 > cc0:
            out[rr0 - rows[0]:rr1 - rows[0], cc0 - cols[0]:cc1 - cols[0]] = level[rr0:rr1, cc0:cc1]
        del level
        return out

    def _inside(self, name: str, rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
        h, w = self._members[name].shape[:2]
        r = np.arange(rows[0], rows[1])
        c = np.arange(cols[0], cols[1])
        return ((r >= 0) & (r < h))[:, None] & ((c >= 0) & (c < w))[None, :]
