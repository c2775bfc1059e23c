"""``write_products``: every map product of a run into one folder.

Files (each written under a temporary name, then renamed):

| file | what |
|---|---|
| trajectory.json, trajectory.tum | SLAM trajectory, lidarmap JSON and TUM |
| dead_reckoning.json, dead_reckoning.tum | odometry-only trajectory, lidarmap JSON and TUM |
| occupancy.png | grid, north up: free white, occupied black, unknown grey |
| occupancy_trajectory.png | the same with dead reckoning (blue) and the SLAM trajectory (red) |
| occupancy.tif | GeoTIFF, float32 probability, -1 = unknown (nodata); local frame or UTM |
| map.pgm, map.yaml | ROS map_server / Nav2 map (trinary) |
| texture.png, texture.tif | ground texture (RGBA, transparent = unseen), when the run made one |
| animation.gif | the map being built, when the run kept snapshots |
| map_points.ply | the map as a point cloud: the scans' returns at the optimised poses, voxel and outlier filtered |
| run.json | config, input, timings, memory, filter stats, accuracy (written last) |
"""

from __future__ import annotations

from pathlib import Path

from PIL import Image

from slam_engine.model.result import SlamResult, Trajectory
from slam_engine.products.animation import write_animation_gif
from slam_engine.products.files import atomic_path
from slam_engine.products.georeference import GeoOrigin, Georeference
from slam_engine.products.geotiff import write_occupancy_geotiff, write_texture_geotiff
from slam_engine.products.map_bundle import BUNDLE_FILE, write_bundle
from slam_engine.products.point_cloud import POINT_CLOUD_FILE, write_map_point_cloud
from slam_engine.products.rendering import (
    PNG_COMPRESS_LEVEL,
    occupancy_rasters,
    texture_image,
    write_occupancy_with_trajectories_png,
)
from slam_engine.products.ros_map import write_ros_map
from slam_engine.products.run_report import build_run_report, to_jsonable, write_run_json
from slam_engine.products.trajectory_files import write_trajectory_json, write_trajectory_tum

MAP_FRAME = "map: local metric frame of the run (x, y in m, theta in rad), origin at the first pose"


def georeference_for(result: SlamResult, geo: GeoOrigin | None) -> Georeference:
    """UTM placement from the geo origin of the first pose, or the local map frame."""
    if geo is None:
        return Georeference.local()
    start = result.trajectory.poses[0] if len(result.trajectory) else [0.0, 0.0, 0.0]
    return Georeference.utm(geo, start)


def accuracy_figures(trajectory: Trajectory, relations=None, ground_truth=None) -> dict | None:
    """Relation errors (``relations``: a path or what ``evaluation.read_relations`` returns) and the
    absolute trajectory error against ``ground_truth`` (a path or a Trajectory), as plain JSON values."""
    if relations is None and ground_truth is None:
        return None
    from slam_engine.evaluation import metrics as evaluation

    figures: dict = {}
    if relations is not None:
        if isinstance(relations, str | Path):
            relations = evaluation.read_relations(relations)
        figures["relations"] = to_jsonable(evaluation.relation_errors(trajectory, relations).as_dict())
    if ground_truth is not None:
        if isinstance(ground_truth, str | Path):
            ground_truth = evaluation.read_ground_truth(ground_truth)
        try:
            figures["ate_m"] = evaluation.absolute_trajectory_error(trajectory, ground_truth)
        except ValueError as exc:  # too few poses matched in time: say so instead of failing the run
            figures["ate_m"], figures["ate_error"] = None, str(exc)
    return figures


def write_products(result: SlamResult, out_dir: str | Path, geo: GeoOrigin | None = None,
                   relations=None, ground_truth=None, log=None,
                   texture_accuracy: dict | None = None, extra_products: list[str] | None = None) -> dict[str, Path]:
    """Write every product of ``result`` into ``out_dir``; returns {file name: path}.

    ``geo`` places the GeoTIFFs in UTM (else the local map frame); ``relations`` / ``ground_truth``
    add accuracy figures to run.json, ``texture_accuracy`` (colour error and placement against a known
    floor, :mod:`slam_engine.texture.accuracy`) as its ``accuracy.texture``; ``log`` (the DriveLog)
    fills run.json's input summary when the result carries none; ``extra_products``: files the caller
    writes beside these, listed in run.json too.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    georef = georeference_for(result, geo)
    config = to_jsonable(result.config)
    written: dict[str, Path] = {}

    def save_image(image, name: str, format: str) -> None:
        with atomic_path(out / name) as tmp:
            image.save(tmp, format=format, compress_level=PNG_COMPRESS_LEVEL)
        written[name] = out / name

    written["trajectory.json"] = write_trajectory_json(result.trajectory, out / "trajectory.json",
                                                       frame=MAP_FRAME, config=config)
    written["trajectory.tum"] = write_trajectory_tum(result.trajectory, out / "trajectory.tum")
    written["dead_reckoning.json"] = write_trajectory_json(result.dead_reckoning, out / "dead_reckoning.json",
                                                           frame=MAP_FRAME, config=config)
    written["dead_reckoning.tum"] = write_trajectory_tum(result.dead_reckoning, out / "dead_reckoning.tum")
    rasters = occupancy_rasters(result.grid)  # rendered once for the PNGs, the GeoTIFF and the ROS map
    save_image(Image.fromarray(rasters.gray), "occupancy.png", "PNG")
    with atomic_path(out / "occupancy_trajectory.png") as tmp:  # streamed: no RGB image of the whole map
        write_occupancy_with_trajectories_png(tmp, result.grid, result.trajectory, result.dead_reckoning, rasters.gray)
    written["occupancy_trajectory.png"] = out / "occupancy_trajectory.png"
    written["occupancy.tif"] = write_occupancy_geotiff(result.grid, out / "occupancy.tif", georef, rasters=rasters)
    pgm, yaml_path = write_ros_map(result.grid, out, "map", rasters=rasters)
    written[pgm.name], written[yaml_path.name] = pgm, yaml_path
    if result.texture is not None:
        save_image(texture_image(result.texture), "texture.png", "PNG")
        written["texture.tif"] = write_texture_geotiff(result.texture, out / "texture.tif", georef)
    if result.snapshots:
        written["animation.gif"] = write_animation_gif(result.snapshots, result.grid, result.trajectory,
                                                       out / "animation.gif")
    if result.bundle is not None:
        written[BUNDLE_FILE] = write_bundle(result.bundle, out / BUNDLE_FILE)
        if len(result.bundle):
            written[POINT_CLOUD_FILE] = write_map_point_cloud(result.bundle, out / POINT_CLOUD_FILE)
    input_summary = result.input_summary or (log.summary() if log is not None else {})
    accuracy = accuracy_figures(result.trajectory, relations, ground_truth)
    if texture_accuracy is not None:
        accuracy = {**(accuracy or {}), "texture": to_jsonable(texture_accuracy)}
    report = build_run_report(result, input_summary=input_summary,
                              georeference=georef.describe(),
                              accuracy=accuracy,
                              products=sorted([*written, *(extra_products or []), "run.json"]), rasters=rasters)
    written["run.json"] = write_run_json(report, out / "run.json")
    return written
