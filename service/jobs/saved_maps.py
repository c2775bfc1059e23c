"""Jobs that start from a saved map ('localize' and 'extend'): which map, and what they write.

The saved map is the ``map_bundle.npz`` product of a finished job of the same owner (a mapping or
extension job, or an uploaded map); a 'localize' job that names none searches the owner's saved maps
(:mod:`slam_engine.multisession.which_map`). The work is the engine's (:mod:`slam_engine.multisession`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from api_schemas.jobs import JobMode, JobStatus
from service.http_errors import Conflict, NotFound
from service.jobs.context import JobContext
from service.jobs.outputs import write_job_products
from service.storage.data_dir import DataDir
from service.storage.store import JobStore
from slam_engine.errors import MapBundleError
from slam_engine.model.drive_log import DriveLog
from slam_engine.progress import WRITING_PRODUCTS, run_fraction

BUNDLE = "map_bundle.npz"
MAX_SEARCHED_MAPS = 50  # a localisation without a named map searches the owner's newest saved maps, at most


def saved_map_path(store: JobStore, data: DataDir, owner: str, map_job_id: str, field: str = "map_job_id") -> Path:
    """The map bundle of job ``map_job_id`` (named by the request's ``field``): NotFound (404) when there is
    no such job for ``owner``, Conflict (409) when it has not succeeded or made no map bundle."""
    job = store.get_job(map_job_id, owner)
    if job is None:
        raise NotFound(f"no job {map_job_id!r} to start from", {"field": field})
    if job.status is not JobStatus.SUCCEEDED or BUNDLE not in job.products:
        raise Conflict(f"job {map_job_id!r} has no saved map to start from (status {job.status}; a succeeded mapping "
                       "or extension job has one)", {"field": field, "status": job.status})
    return data.resolve(str(Path("jobs") / job.id / job.products[BUNDLE]))


def saved_map_paths(store: JobStore, data: DataDir, owner: str) -> list[tuple[str, Path]]:
    """(job id, map bundle) of ``owner``'s newest MAX_SEARCHED_MAPS finished jobs with a saved map;
    Conflict (409) when there is none."""
    found: list[tuple[str, Path]] = []
    offset = 0
    while len(found) < MAX_SEARCHED_MAPS:
        rows, total = store.list_jobs(owner, None, JobStatus.SUCCEEDED, 200, offset)
        found += [(job.id, data.resolve(str(Path("jobs") / job.id / job.products[BUNDLE])))
                  for job in rows if BUNDLE in job.products]
        offset += len(rows)
        if not rows or offset >= total:
            break
    if not found:
        raise Conflict("no saved map to localise in: map a drive first, or upload a map, and name it as "
                       "'map_job_id'", {"field": "map_job_id"})
    return found[:MAX_SEARCHED_MAPS]


def job_mode(config: dict[str, Any]) -> JobMode:
    return JobMode(config.get("mode", JobMode.MAP))


def run_from_saved_map(ctx: JobContext, log: DriveLog, progress: Any) -> None:
    """A 'localize' or 'extend' job over ``log`` once its input is read (``progress``: the run's progress
    callback, for the mapping part of an extension)."""
    from service.jobs.settings import engine_config
    from slam_engine.products.map_bundle import read_bundle

    config = engine_config(ctx.job.config)
    if ctx.job.config.get("map_job_id") is None:  # a localisation in whichever saved map the drive is in
        try:
            paths = saved_map_paths(ctx.store, ctx.data, ctx.job.owner)
        except Conflict as error:  # every saved map was deleted after this job was queued
            raise MapBundleError(str(error)) from None
        _localize_in_any(ctx, [(job_id, read_bundle(path)) for job_id, path in paths], log, config)
        return
    try:
        path = saved_map_path(ctx.store, ctx.data, ctx.job.owner, str(ctx.job.config["map_job_id"]))
    except (NotFound, Conflict) as error:  # the saved map's job was deleted after this job was queued
        raise MapBundleError(str(error)) from None
    bundle = read_bundle(path)
    if job_mode(ctx.job.config) is JobMode.LOCALIZE:
        _localize(ctx, bundle, log, config)
    else:
        _extend(ctx, bundle, log, config, progress)


def _localize(ctx: JobContext, bundle: Any, log: DriveLog, config: Any) -> None:
    from slam_engine.frontend.particle_filter import engine_threads
    from slam_engine.multisession.localization import localize_log, refusal_reason

    # the worker's engine threads (LIDARMAP_THREADS, 1 unless set), as its mapping jobs use
    drive, result = localize_log(bundle, log, config, threads=engine_threads())
    _writing(ctx, len(drive))
    if not result.localised:
        raise MapBundleError("refused: the drive has no place in the saved map: "
                             f"{refusal_reason(result, config.localization.min_score)}")
    _write_localization(ctx, bundle, drive, result, result.summary(), config)


def _localize_in_any(ctx: JobContext, maps: list[tuple[str, Any]], log: DriveLog, config: Any) -> None:
    """The drive localised in the saved map it is in, among ``maps`` ((job id, bundle), newest first)."""
    from slam_engine.frontend.particle_filter import engine_threads
    from slam_engine.multisession.which_map import localize_in_maps

    which = localize_in_maps(maps, log, config, threads=engine_threads())
    _writing(ctx, len(which.drive))
    if which.chosen is None or which.result is None:
        raise MapBundleError(f"refused: the drive is in none of the {len(maps)} saved maps "
                             f"({which.refusal_reason(config.localization.min_score, 'job ')})")
    bundle = dict(maps)[which.tries[which.chosen].name]
    _write_localization(ctx, bundle, which.drive, which.result,
                        {**which.result.summary(), "which_map": which.summary()}, config)


def _writing(ctx: JobContext, scans: int) -> None:
    """The job's progress: every one of its ``scans`` placed, the products being written."""
    ctx.progress(scans, scans, force=True, stage=WRITING_PRODUCTS, fraction=run_fraction(WRITING_PRODUCTS, 0.0))


def _write_localization(ctx: JobContext, bundle: Any, drive: Any, result: Any, summary: dict, config: Any) -> None:
    """A localisation's products (the drive over ``bundle``'s map, its trajectory, confidence and
    ``summary``), listed in the store."""
    from service.jobs.outputs import product_names
    from slam_engine.multisession.changes import localization_changes
    from slam_engine.products.multisession import localization_image, saved_map_grid, write_localization

    assert result.trajectory is not None
    grid = saved_map_grid(bundle, config)
    image = localization_image(grid, result.trajectory, drive.hits, result.tracked)
    found = localization_changes(grid, drive, result, config.changes)
    files = write_localization(ctx.out_dir / "products", summary, result.trajectory, result.confidence, image,
                               changes=None if found is None else (found, grid))
    ctx.store.set_products(ctx.job_id, product_names(files, ctx.out_dir))


def _extend(ctx: JobContext, bundle: Any, log: DriveLog, config: Any, progress: Any) -> None:
    from service.jobs.outputs import session_geo
    from slam_engine.frontend.particle_filter import engine_threads
    from slam_engine.multisession.changes import extension_changes
    from slam_engine.multisession.joining import join
    from slam_engine.multisession.localization import refusal_reason
    from slam_engine.pipeline import run_slam
    from slam_engine.products.changes import write_changes
    from slam_engine.products.export import georeference_for
    from slam_engine.products.multisession import drives_image, joined_result, save_png

    own = run_slam(log, config, progress=progress)
    assert own.bundle is not None  # a run with scans always makes one
    joined = join(bundle, own.bundle, config, threads=engine_threads())
    if not joined.connected:
        raise MapBundleError("refused: the drive could not be placed in the saved map: "
                             f"{refusal_reason(joined.placement, config.localization.min_score)}; map it on its "
                             "own, or extend with a drive that overlaps the map")
    products = ctx.out_dir / "products"
    extra = {"drives.png": save_png(drives_image(joined.grid, joined.trajectory, joined.trajectory_drive),
                                    products / "drives.png")}
    found = extension_changes(joined, config)
    result = joined_result(joined, config, own, None if found is None else found[0])
    if found is not None:  # placed as write_job_products places the map's GeoTIFF
        extra.update(write_changes(products, *found, georeference_for(result, session_geo(ctx))))
    write_job_products(ctx, result, log, extra=extra)


def run_merge_job(ctx: JobContext) -> None:
    """A 'merge' job: the saved maps of ``map_job_id`` and ``merge_job_id`` made one map (the first's frame
    kept), written as a mapping job's products with ``drives.png``; refused (MapBundleError) when they do
    not overlap."""
    from service.jobs.outputs import product_names
    from service.jobs.products import GRID_FILE, save_grid
    from service.jobs.settings import engine_config
    from slam_engine.frontend.particle_filter import engine_threads
    from slam_engine.multisession.joining import join
    from slam_engine.multisession.localization import refusal_reason
    from slam_engine.products.map_bundle import read_bundle
    from slam_engine.products.multisession import write_joined_products

    config = engine_config(ctx.job.config)
    bundles = []
    for field in ("map_job_id", "merge_job_id"):
        try:
            bundles.append(read_bundle(saved_map_path(ctx.store, ctx.data, ctx.job.owner, str(ctx.job.config[field]),
                                                      field)))
        except (NotFound, Conflict) as error:  # the saved map's job was deleted after this job was queued
            raise MapBundleError(str(error)) from None
    ctx.store.set_input(ctx.job_id, {"source": "map", "map_job_id": ctx.job.config["map_job_id"],
                                     "merge_job_id": ctx.job.config["merge_job_id"]})
    joined = join(bundles[0], bundles[1], config, threads=engine_threads())
    if not joined.connected:
        raise MapBundleError("refused: the maps do not overlap: the second could not be placed in the first: "
                             f"{refusal_reason(joined.placement, config.localization.min_score)}")
    ctx.stage(WRITING_PRODUCTS)
    files = write_joined_products(joined, config, ctx.out_dir / "products")
    save_grid(joined.grid, ctx.out_dir / GRID_FILE)
    ctx.store.set_products(ctx.job_id, product_names(files, ctx.out_dir))
