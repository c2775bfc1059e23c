"""What every job writes, whatever its input: the live map while it runs (:class:`LiveMap`) and, at the
end, its products (:func:`write_job_products`), listed in the store under the names the API serves."""

from __future__ import annotations

import shutil
from pathlib import Path

from service.jobs.context import JobContext
from service.jobs.products import GRID_FILE, TEXTURE_FILE, save_grid, save_texture
from service.storage.data_dir import write_atomic
from service.storage.rows import SessionRow
from slam_engine.errors import LogFormatError
from slam_engine.model.drive_log import DriveLog
from slam_engine.model.result import MapSnapshot, SlamResult
from slam_engine.products import GeoOrigin, write_trajectory_json
from slam_engine.products.rendering import occupancy_image, png_bytes


def job_session(ctx: JobContext) -> SessionRow:
    """The job's session row (the job fails when the session was deleted meanwhile)."""
    session = ctx.store.get_session(ctx.job.session_id, ctx.job.owner)
    if session is None:
        raise LogFormatError("the job's session was deleted")
    return session


class LiveMap:
    """Writes the map so far (PNG and the tile grid) whenever the run hands over a snapshot newer than
    the one written last (never an older one: a live job mixes the filter's periodic snapshots with
    the map as it stands when it has caught up); files are replaced atomically, so readers never see
    half a file."""

    def __init__(self, live_dir: Path):
        self.live_dir = live_dir
        self._last_scan_index: int | None = None

    def update(self, snapshot: MapSnapshot | None) -> bool:
        """Write ``snapshot`` unless it is None or not newer than the one written last; whether it wrote."""
        if snapshot is None or (self._last_scan_index is not None and snapshot.scan_index <= self._last_scan_index):
            return False
        self._last_scan_index = snapshot.scan_index
        self.live_dir.mkdir(parents=True, exist_ok=True)
        save_grid(snapshot.grid, self.live_dir / GRID_FILE)
        write_atomic(self.live_dir / "occupancy.png", png_bytes(occupancy_image(snapshot.grid)))
        write_trajectory_json(snapshot.trajectory, self.live_dir / "trajectory.json", frame="map (so far)")
        return True


def write_job_products(ctx: JobContext, result: SlamResult, log: DriveLog, extra: dict[str, Path] | None = None
                       ) -> None:
    """Write a finished run's products into the job's folder, list them in the store (with ``extra``:
    products the caller wrote there itself), drop the live snapshot."""
    from slam_engine.products import write_products
    from slam_engine.progress import WRITING_PRODUCTS

    ctx.stage(WRITING_PRODUCTS)
    server_folder = f"{ctx.data.root}/"  # no server path in run.json, whatever said it
    result.warnings[:] = [warning.replace(server_folder, "") for warning in result.warnings]
    peak = ctx.peak_memory_bytes()
    if peak:  # this job's own peak (the engine's getrusage figure spans the worker's whole life)
        result.peak_memory_bytes = peak
    out_dir = ctx.out_dir
    files = {**(extra or {}), **write_products(result, out_dir / "products", geo=session_geo(ctx), log=log,
                                               extra_products=sorted(extra or {}))}
    save_grid(result.grid, out_dir / GRID_FILE)
    if result.texture is not None:
        save_texture(result.texture, out_dir / TEXTURE_FILE)
    ctx.store.set_products(ctx.job_id, product_names(files, out_dir))
    shutil.rmtree(ctx.data.live_dir(ctx.job_id), ignore_errors=True)


def session_geo(ctx: JobContext) -> GeoOrigin | None:
    """Where the job's session started on Earth, when its owner said so (None: the local map frame)."""
    session = job_session(ctx)
    return None if session.geo is None else GeoOrigin(latitude_deg=session.geo["lat_deg"],
                                                      longitude_deg=session.geo["lon_deg"],
                                                      heading_deg=session.geo["heading_deg"])


def product_names(files: dict[str, Path], out_dir: Path) -> dict[str, str]:
    """API product name -> file path relative to the job folder, for the files write_products made."""
    return {Path(path).name: str(Path(path).resolve().relative_to(out_dir.resolve())) for path in files.values()}
