"""A job's peak memory, estimated from its configuration and log before it runs (so that a service
can refuse or bound a job it cannot hold).

Where a run's memory goes (whole process, measured on the benchmark logs):

- the imported libraries (numba/llvmlite, numpy, scipy, pydantic, Pillow, tifffile): ~130 MB, and
  the numba kernels loaded from the cache: ~65 MB;
- the log: its arrays, plus the parser's temporaries while loading (about 3x the arrays);
- the map: the particles' copy-on-write tile pool (the area seen, times the fraction of tiles
  particles hold privately), the per-particle tile tables, the best particle's dense grid
  (float32) and the products rendered from it (grey, RGB, probability rasters: ~12 bytes a cell);
- the newest full-resolution map snapshot (older ones are pooled to <= 800 cells a side).

The map's area is the dead-reckoning track's bounding box grown by the range the map uses; drift
makes the real area differ, so the estimate errs high on purpose (:data:`MARGIN`).
"""

from __future__ import annotations

import numpy as np

from slam_engine.config import SlamConfig
from slam_engine.drive_log import DriveLog
from slam_engine.grid import N_LEVELS, POOL_DTYPE, TILE

# interpreter, imports (~130 MB; GTSAM and scipy.sparse for the back end), numba kernels (~65 MB loaded; more
# while compiling). A tiny run measured 320-410 MB in a clean process but 770 MB inside the full test session
# (cause not found): the base covers the larger figure.
BASE_BYTES = 650 * 1024**2
LOG_LOAD_FACTOR = 3.0  # peak while loading / the log's arrays
DENSE_BYTES_PER_CELL = 4 + 4 + 12  # final grid float32 + newest snapshot float32 + product rasters
PRIVATE_TILE_FRACTION = 0.03  # per particle: private tiles beyond the shared map (pool ~1.8x the area at 30)
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


def map_extent_m(log: DriveLog, config: SlamConfig) -> tuple[float, float]:
    """(width, height) [m] of the area the map will likely cover: the dead-reckoning track's
    bounding box grown on every side by the 95th percentile of the returns' ranges (at most
    ``max_range_m``). Odometry drift makes the box larger than the map: an estimate on the high side."""
    from slam_engine.odometry import dead_reckoning

    reach = 0.0
    if log.scans is not None and log.lidar is not None and len(log.scans):
        ranges = log.scans.ranges_m[:: max(1, len(log.scans) // 500)]  # a sample of scans is enough
        returns = ranges[np.isfinite(ranges) & (ranges > 0) & (ranges < log.lidar.range_max_m)]
        if returns.size:
            reach = min(float(np.percentile(returns, REACH_PERCENTILE)), config.grid.max_range_m)
    try:
        poses = dead_reckoning(log).poses
    except Exception:  # no odometry: nothing will be mapped beyond one scan
        poses = np.zeros((1, 3))
    span = poses[:, :2].max(axis=0) - poses[:, :2].min(axis=0) if len(poses) else np.zeros(2)
    return float(span[0] + 2 * reach), float(span[1] + 2 * reach)


def estimate_job_memory_bytes(config: SlamConfig, log: DriveLog) -> int:
    """Estimated peak resident memory [bytes] of mapping ``log`` with ``config`` and writing its
    products, for the whole process (see the module docstring for the model)."""
    width_m, height_m = map_extent_m(log, config)
    res = config.grid.resolution_m
    cells = (width_m / res) * (height_m / res)
    tiles = cells / TILE**2
    pool = tiles * (1.0 + PRIVATE_TILE_FRACTION * config.particles) * TILE_BYTES
    tables = tiles * config.particles * 5  # int32 table + uint8 marks per particle
    dense = cells * DENSE_BYTES_PER_CELL
    total = BASE_BYTES + LOG_LOAD_FACTOR * log_array_bytes(log) + pool + tables + dense
    return int(MARGIN * total)
