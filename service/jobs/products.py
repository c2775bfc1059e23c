"""Where a job's products lie and how they are served: the final files (listed in the job row by
the worker) and, while the job runs, the live snapshot (``live/occupancy.png`` and
``live/grid.npz``, replaced atomically by the worker)."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from api_schemas.jobs import JobStatus
from service.http_errors import NotFound, NotReady
from service.jobs.context import STAGE_FILE
from service.storage.data_dir import DataDir
from service.storage.rows import JobRow
from slam_engine.model.result import OccupancyGrid, TextureMap
from slam_engine.products.tile_pyramid import TilePyramid, open_map, write_tile_pyramid

MEDIA_TYPES = {  # every file product a job can list; each is served at GET /v1/jobs/{id}/{name}
    "trajectory.json": "application/json", "trajectory.tum": "text/plain",
    "dead_reckoning.json": "application/json", "dead_reckoning.tum": "text/plain",
    "occupancy.png": "image/png", "occupancy_trajectory.png": "image/png", "occupancy.tif": "image/tiff",
    "map.yaml": "application/yaml",
    "map.pgm": "image/x-portable-graymap", "texture.png": "image/png", "texture.tif": "image/tiff",
    "animation.gif": "image/gif", "run.json": "application/json",
    "map_points.ply": "application/octet-stream",  # the map as a point cloud (binary PLY)
    "map_bundle.npz": "application/zip",  # the map for later drives: localise, extend, merge (docs/map-bundle.md)
    "drives.png": "image/png", "localization.png": "image/png", "confidence.json": "application/json",
    "changes.png": "image/png", "changes.geojson": "application/geo+json",
    "poses.jsonl": "application/x-ndjson",  # a live localisation's reports, one JSON object a line
}
LIVE_FILES = {"occupancy.png": "occupancy.png", "grid.npz": "grid.npz", "trajectory.json": "trajectory.json"}
GRID_FILE, TEXTURE_FILE = "grid.npz", "texture.npz"  # the service's own copies for tiles


COMPILING_FILE = "compiling"  # in a running job's live folder while the engine compiles its kernels


def engine_compiling(data: DataDir, job: JobRow) -> bool:
    """Whether a running job's engine is compiling its numba kernels right now (first use without a
    warm cache: no scans are mapped meanwhile, so no ETA can be given)."""
    return job.status is JobStatus.RUNNING and (data.live_dir(job.id) / COMPILING_FILE).exists()


def running_stage(data: DataDir, job: JobRow) -> str | None:
    """What a running job does now (its worker's last stage, :data:`service.jobs.context.STAGE_FILE`)."""
    if job.status is not JobStatus.RUNNING:
        return None
    try:
        return (data.job_dir(job.id) / STAGE_FILE).read_text()[:100] or None
    except OSError:
        return None


def live_product_names(data: DataDir, job: JobRow) -> list[str]:
    """Products a running job can already show."""
    if job.status is not JobStatus.RUNNING:
        return []
    live = data.live_dir(job.id)
    names = []
    if (live / "occupancy.png").exists():
        names.append("occupancy.png")
    if (live / GRID_FILE).exists():
        names.append("tiles/occupancy")
    if (live / "trajectory.json").exists():
        names.append("trajectory.json")
    return names


def product_path(data: DataDir, job: JobRow, name: str) -> Path:
    """The file of product ``name``: final when the job succeeded, the live snapshot while it runs."""
    stored = job.products.get(name)
    if stored is not None and job.status is JobStatus.SUCCEEDED:
        path = data.resolve(str(Path("jobs") / job.id / stored))
        if path.exists():
            return path
    if job.status is JobStatus.RUNNING and name in LIVE_FILES:
        path = data.live_dir(job.id) / LIVE_FILES[name]
        if path.exists():
            return path
    if job.status is JobStatus.SUCCEEDED:
        raise NotFound(f"this job has no {name!r} product (e.g. no camera for a texture)",
                       {"product": name, "available": sorted(job.products)})
    raise NotReady(f"{name!r} is not available while the job is {job.status}",
                   {"product": name, "status": job.status})


def save_grid(grid: OccupancyGrid, path: Path) -> None:
    """Write a grid as the tile source: a tile pyramid file, atomically (the map and its pooled levels)."""
    write_tile_pyramid(grid, path)


def save_texture(texture: TextureMap, path: Path) -> None:
    write_tile_pyramid(texture, path)


_build_lock = threading.Lock()  # one legacy map converted at a time: the API holds one map, at most


def open_pyramid(path: Path) -> TilePyramid:
    """The tile pyramid at ``path``. A map file written before pyramids (no levels) is converted once
    into ``<name>.pyramid.npz`` beside it, however many requests ask at once (the others wait for it)."""
    pyramid = TilePyramid.open(path)
    if pyramid is not None:
        return pyramid
    converted = path.with_name(path.stem + ".pyramid.npz")
    with _build_lock:
        if not converted.exists() or converted.stat().st_mtime_ns < path.stat().st_mtime_ns:
            write_tile_pyramid(open_map(path) or _load_map(path), converted)  # mapped: read band by band
    pyramid = TilePyramid.open(converted)
    assert pyramid is not None
    return pyramid


def _load_map(path: Path) -> OccupancyGrid | TextureMap:
    with np.load(path) as z:
        placement = {"resolution_m": float(z["resolution_m"]), "origin_x_m": float(z["origin_x_m"]),
                     "origin_y_m": float(z["origin_y_m"])}
        if "log_odds" in z.files:
            return OccupancyGrid(log_odds=z["log_odds"], **placement)
        return TextureMap(colors=z["colors"], counts=z["counts"], **placement)


def tile_source(data: DataDir, job: JobRow, layer: str) -> tuple[TilePyramid, tuple]:
    """The tile pyramid that tiles of ``layer`` are cut from (read by window, never whole), and a version
    key for the tile cache (changes whenever the file does)."""
    job_dir = data.job_dir(job.id)
    if job.status is JobStatus.SUCCEEDED:
        path = job_dir / (GRID_FILE if layer == "occupancy" else TEXTURE_FILE)
        if not path.exists():
            raise NotFound(f"this job has no {layer} layer", {"layer": layer})
        pyramid = open_pyramid(path)
        return pyramid, (str(path), pyramid.version)
    if job.status is JobStatus.RUNNING and layer == "occupancy":
        path = data.live_dir(job.id) / GRID_FILE
        if path.exists():
            pyramid = open_pyramid(path)
            return pyramid, (str(path), pyramid.version)
    raise NotReady(f"no {layer} tiles while the job is {job.status}", {"layer": layer, "status": job.status})

