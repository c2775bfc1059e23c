"""A job's peak memory, estimated from its configuration and log before it runs (so that a service
can refuse or bound a job it cannot hold), and the measured peak (:func:`peak_resident_bytes`).

Where a run's memory goes (whole process, measured on the benchmark logs):

- the interpreter and the libraries the front end needs (numpy, numba/llvmlite, pydantic): ~115 MB,
  numba's compiler context and the kernels loaded from the cache: ~70 MB. The back end's GTSAM
  (~40 MB) and the products' libraries are imported when first used, after the front end's peak:
  every run writes a GeoTIFF (rasterio and GDAL, 20-35 MB) and a point cloud (Open3D, 60-90 MB),
  so the product phase holds :data:`PRODUCT_LIBRARIES_BYTES` more; OpenCV (~15 MB) only for camera
  data, pyproj only for geo origins;
- the log: its arrays, plus the parser's temporaries while loading (about 3x the arrays);
- per scan: the key frames' ranges (the log's own rows), the back end's end points and the
  trajectories (:data:`SCAN_BYTES_PER_BEAM` a beam, an upper bound);
- the particles' copy-on-write tile pool: the tiles of the area seen, plus the tiles each particle
  holds privately (touched since its map diverged: up to about :data:`PRIVATE_TILES_PER_PARTICLE`,
  fewer on a small map), with the slack left as the pool grows (:data:`POOL_SLACK`); the per-particle tile tables;
- the product map: the final grid (float32) and, while the products are written, its grey, ROS
  and track-mask rasters (one byte a cell each; the GeoTIFF and the PNG with the tracks are
  streamed), and the product map's own single-particle tiles: :data:`DENSE_BYTES_PER_CELL`;
- snapshots: the newest pooled to <= 2048 cells a side, older ones compressed (a few MB).

The map's area is the dead-reckoning track's bounding box grown by the range the map uses; drift
makes the real area differ, so the estimate errs high on purpose (:data:`MARGIN`; on the benchmark
logs it is 1.2-2.4x the measured peak).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam_engine.config import SlamConfig
from slam_engine.frontend.tile_layout import N_LEVELS, POOL_DTYPE, POOL_GROWTH_DIVISOR, TILE
from slam_engine.model.drive_log import DriveLog

# interpreter, libraries, numba's compiler context and kernels: a short simulated run (10 particles)
# peaked at 211-240 MB in a fresh process (its own high-water mark: see peak_resident_bytes), and at
# 289 MB inside CI's session
BASE_BYTES = 250 * 1024**2
# rasterio/GDAL and Open3D, imported to write the products (a fresh install's process: +35 and +87 MB)
PRODUCT_LIBRARIES_BYTES = 120 * 1024**2
LOG_LOAD_FACTOR = 3.0  # peak while loading / the log's arrays
SCAN_BYTES_PER_BEAM = 48  # key frames, the back end's end points (float64 x, y, and their copies)
DENSE_BYTES_PER_CELL = 4 + 3 + 3  # final grid float32 + product rasters + the product map's tiles
PRIVATE_TILES_PER_PARTICLE = 256  # intel: 7 610 tiles in use at most with 30 particles on a 169-tile map
POOL_SLACK = 1.0 + 1.0 / POOL_GROWTH_DIVISOR
MARGIN = 1.25
TILE_BYTES = sum((TILE >> k) ** 2 for k in range(N_LEVELS)) * np.dtype(POOL_DTYPE).itemsize


def peak_resident_bytes() -> int:
    """This process's peak resident memory so far [bytes]: the kernel's high-water mark of its own
    address space (``VmHWM``). Not ``getrusage``'s ``ru_maxrss``: on Linux, a process started by
    another (fork or vfork, then exec) counts the parent's resident size at that moment into its
    ``ru_maxrss``, so a small run started from a large process (a long test session) seemed to peak
    at that process's size. ``ru_maxrss`` only where ``/proc`` is missing."""
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    import resource

    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def log_array_bytes(log: DriveLog) -> int:
    """Bytes of the log's numpy arrays (every stream's fields)."""
    total = 0
    for stream in (log.scans, log.odometry, log.encoders, log.gyro):
        if stream is None:
            continue
        total += sum(v.nbytes for v in vars(stream).values() if isinstance(v, np.ndarray))
    return total


REACH_PERCENTILE = 95  # the map reaches about this percentile of the scans' return ranges past the track


@dataclass(frozen=True)
class DriveFigures:
    """What a drive's memory depends on, measured once from its log (a service stores them at upload):
    the dead-reckoning track's bounding box [m], how far past it the returns reach (the 95th percentile
    of their ranges [m]), the beams of all scans and the bytes of the log's arrays."""

    track_width_m: float
    track_height_m: float
    reach_m: float
    beams: int
    array_bytes: int


def drive_figures(log: DriveLog) -> DriveFigures:
    """The figures of ``log`` (see :class:`DriveFigures`)."""
    from slam_engine.frontend.odometry import dead_reckoning

    reach = 0.0
    if log.scans is not None and log.lidar is not None and len(log.scans):
        ranges = log.scans.ranges_m[:: max(1, len(log.scans) // 500)]  # a sample of scans is enough
        returns = ranges[np.isfinite(ranges) & (ranges > 0) & (ranges < log.lidar.range_max_m)]
        if returns.size:
            reach = float(np.percentile(returns, REACH_PERCENTILE))
    try:
        poses = dead_reckoning(log).poses
    except Exception:  # no odometry: nothing will be mapped beyond one scan
        poses = np.zeros((1, 3))
    span = poses[:, :2].max(axis=0) - poses[:, :2].min(axis=0) if len(poses) else np.zeros(2)
    beams = 0 if log.scans is None else int(np.asarray(log.scans.ranges_m).size)
    return DriveFigures(float(span[0]), float(span[1]), reach, beams, log_array_bytes(log))


def map_extent_m(log: DriveLog | DriveFigures, config: SlamConfig) -> tuple[float, float]:
    """(width, height) [m] of the area the map will likely cover: the dead-reckoning track's
    bounding box grown on every side by the 95th percentile of the returns' ranges (at most
    ``max_range_m``). Odometry drift makes the box larger than the map: an estimate on the high side."""
    figures = log if isinstance(log, DriveFigures) else drive_figures(log)
    reach = min(figures.reach_m, config.grid.max_range_m)
    return figures.track_width_m + 2 * reach, figures.track_height_m + 2 * reach


def estimate_job_memory_bytes(config: SlamConfig, log: DriveLog | DriveFigures) -> int:
    """Estimated peak resident memory [bytes] of mapping ``log`` (or a log of these figures) with
    ``config`` and writing its products, for the whole process (see the module docstring for the
    model): it grows with the drive's extent (the map's cells) and its scan count (its beams)."""
    figures = log if isinstance(log, DriveFigures) else drive_figures(log)
    width_m, height_m = map_extent_m(figures, config)
    res = config.grid.resolution_m
    cells = (width_m / res) * (height_m / res)
    tiles = cells / TILE**2
    private = config.particles * min(tiles, PRIVATE_TILES_PER_PARTICLE)
    pool = (tiles + private) * TILE_BYTES * POOL_SLACK
    tables = tiles * config.particles * 5  # int32 table + uint8 marks per particle
    dense = cells * DENSE_BYTES_PER_CELL
    total = (BASE_BYTES + PRODUCT_LIBRARIES_BYTES + LOG_LOAD_FACTOR * figures.array_bytes
             + SCAN_BYTES_PER_BEAM * figures.beams + pool + tables + dense)
    return int(MARGIN * total)
