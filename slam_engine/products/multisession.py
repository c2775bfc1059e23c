"""Products of the runs that use a saved map: a localisation (its trajectory in the map's frame with a
confidence per pose, ``run.json``, and ``localization.png``: the drive's scans drawn over the saved map)
and the drawing of a map built from several drives (``drives.png``: each drive's trajectory in its own
colour over the joint map)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image, ImageDraw

from slam_engine.backend.map_builder import render_occupancy
from slam_engine.config import SlamConfig
from slam_engine.evaluation.consistency import WARNING_START
from slam_engine.model.map_bundle import MapBundle
from slam_engine.model.poses import compose, place_points
from slam_engine.model.result import OccupancyGrid, ScanStats, SlamResult, Trajectory
from slam_engine.multisession.changes import ChangeMap, extension_changes
from slam_engine.products.changes import write_changes
from slam_engine.products.export import accuracy_figures, write_products
from slam_engine.products.files import atomic_path, write_text_atomic
from slam_engine.products.georeference import Georeference
from slam_engine.products.rendering import PNG_COMPRESS_LEVEL, map_pixels, occupancy_rasters
from slam_engine.products.run_report import to_jsonable
from slam_engine.products.trajectory_files import write_trajectory_json, write_trajectory_tum

SAVED_MAP_FRAME = "map: the saved map's frame (x, y in m, theta in rad), origin at its first drive's first pose"
if TYPE_CHECKING:
    from slam_engine.multisession.joining import JoinedMap

# one colour per drive (the first map's drive first), cycled
DRIVE_RGB = ((220, 30, 30), (30, 110, 230), (20, 160, 60), (230, 140, 0), (150, 60, 200), (0, 170, 170))
MATCHED_RGB = (220, 30, 30)  # a localised scan's end points where the scan matched the map
CARRIED_RGB = (30, 110, 230)  # ... where it was carried by the drive's own motion


def saved_map_grid(bundle: MapBundle, config: SlamConfig) -> OccupancyGrid:
    """The occupancy grid of a saved map, rendered from its key frames' scans at their poses."""
    grid_config = config.grid.model_copy(update={"resolution_m": bundle.resolution_m})
    return render_occupancy(bundle.scans(), bundle.poses, bundle.origin_v, grid_config)


def drives_image(grid: OccupancyGrid, trajectory: Trajectory, drive: np.ndarray) -> Image.Image:
    """The map with each drive's trajectory (``drive`` (N,) numbers its poses) in its own colour."""
    image = Image.fromarray(occupancy_rasters(grid).gray).convert("RGB")
    draw = ImageDraw.Draw(image)
    for number in np.unique(drive):
        poses = trajectory.poses[drive == number]
        if len(poses) > 1:
            draw.line([tuple(p) for p in map_pixels(grid, poses)], fill=DRIVE_RGB[int(number) % len(DRIVE_RGB)],
                      width=2)
    return image


def localization_image(grid: OccupancyGrid, trajectory: Trajectory, hits: list[np.ndarray],
                       tracked: np.ndarray) -> Image.Image:
    """The saved map with the localised drive's end points (red where its scan matched the map, blue
    where the drive's own motion carried it) and its trajectory (black)."""
    image = Image.fromarray(occupancy_rasters(grid).gray).convert("RGB")
    draw = ImageDraw.Draw(image)
    for pose, points, matched in zip(trajectory.poses, hits, tracked, strict=True):
        pixels = map_pixels(grid, np.column_stack([place_points(pose, points), np.zeros(len(points))]))
        draw.point([tuple(p) for p in pixels], fill=MATCHED_RGB if matched else CARRIED_RGB)
    if len(trajectory) > 1:
        draw.line([tuple(p) for p in map_pixels(grid, trajectory.poses)], fill=(0, 0, 0), width=1)
    return image


def save_png(image: Image.Image, path: Path) -> Path:
    with atomic_path(path) as tmp:
        image.save(tmp, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
    return path


def write_localization(out_dir: str | Path, summary: dict, trajectory: Trajectory | None, confidence: np.ndarray,
                       image: Image.Image | None, relations=None, ground_truth=None,
                       changes: tuple[ChangeMap, OccupancyGrid] | None = None) -> dict[str, Path]:
    """A localisation's products in ``out_dir``: ``trajectory.tum`` / ``trajectory.json`` (map frame),
    ``confidence.json`` (each pose's match score, 0-1), ``localization.png``, ``run.json`` (the
    summary, with accuracy figures when ``relations`` / ``ground_truth`` are given) and, given the
    change map and the saved map's grid (``changes``), ``changes.png`` / ``changes.geojson`` with
    run.json's ``changes``. A refused drive gets ``run.json`` only."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: dict[str, Path] = {}
    report: dict = {"format": "lidarmap-localization", "version": 1, "frame": SAVED_MAP_FRAME,
                    "localization": to_jsonable(summary)}
    if trajectory is not None:
        written["trajectory.tum"] = write_trajectory_tum(trajectory, out / "trajectory.tum")
        written["trajectory.json"] = write_trajectory_json(trajectory, out / "trajectory.json", frame=SAVED_MAP_FRAME)
        confidence_doc = {"t_s": [round(float(t), 6) for t in trajectory.t_s],
                          "confidence": [round(float(c), 4) for c in confidence]}
        written["confidence.json"] = write_text_atomic(out / "confidence.json", json.dumps(confidence_doc) + "\n")
        report["accuracy"] = accuracy_figures(trajectory, relations, ground_truth)
    if image is not None:
        written["localization.png"] = save_png(image, out / "localization.png")
    if changes is not None:
        written.update(write_changes(out, *changes))
        report["changes"] = changes[0].summary()
    report["products"] = sorted([*written, "run.json"])
    written["run.json"] = write_text_atomic(out / "run.json", json.dumps(to_jsonable(report), indent=1) + "\n")
    return written


def joined_result(joined: JoinedMap, config: SlamConfig, base_result: SlamResult | None = None,
                  changes: ChangeMap | None = None) -> SlamResult:
    """A joint map (an extended or a merged one) as a run's result, for :func:`write_products`: its
    trajectory over every connected drive (in time order), grid and bundle; ``base_result``: the new
    drive's own run, whose statistics and warnings it keeps, and whose dead reckoning is moved to where
    the drive was placed (kept as the trajectory when it was not); ``changes``: the new drive's change
    map against the saved map (run.json's ``changes``)."""
    order = np.argsort(joined.trajectory.t_s, kind="stable")
    trajectory = Trajectory(joined.trajectory.t_s[order], joined.trajectory.poses[order])
    summary = {"multisession": joined.summary, "key_frames": len(joined.bundle), "drives": joined.bundle.drives}
    if changes is not None:
        summary["changes"] = changes.summary()
    warnings = [] if base_result is None else [w for w in base_result.warnings if not w.startswith(WARNING_START)]
    if joined.consistency is not None:  # the joint map's, not the new drive's own map's
        summary["map_consistency"] = joined.consistency.as_dict()
        if (inconsistent := joined.consistency.warning()) is not None:
            warnings.append(inconsistent)
    if base_result is None:
        empty = np.zeros(0)
        stats = ScanStats(empty, empty, np.zeros(0, bool), empty, np.zeros(0, bool), empty)
        return SlamResult(trajectory=trajectory, dead_reckoning=trajectory, grid=joined.grid, scan_stats=stats,
                          config=config, wall_time_s=joined.wall_time_s, input_summary=summary, bundle=joined.bundle,
                          warnings=warnings)
    placed = joined.placement.T_map_from_drive
    odometry = base_result.dead_reckoning
    dead_reckoning = trajectory if placed is None else Trajectory(odometry.t_s, compose(placed, odometry.poses))
    own_loops = base_result.input_summary.get("loop_closing")
    if isinstance(own_loops, dict) and "closures" in own_loops:
        summary["loop_closing"] = _closures_on_the_joint_map(own_loops, joined, base_result)
    return dataclasses.replace(base_result, trajectory=trajectory, grid=joined.grid, bundle=joined.bundle,
                               texture=None, snapshots=[], dead_reckoning=dead_reckoning, warnings=warnings,
                               input_summary={**base_result.input_summary, **summary})


def _closures_on_the_joint_map(loop_summary: dict, joined: JoinedMap, own: SlamResult) -> dict:
    """The new drive's own loop-closing summary with each closure's two key frames placed where they
    ended in the joint map (``node_xy_m``, ``anchor_xy_m`` [m, map frame]: what the viewer draws; they
    were the drive's own frame's). The drive's key frames are the joint bundle's last ones, in order;
    a drive not placed in the map keeps its counts but lists no closures (its frame is not the map's)."""
    out = dict(loop_summary)
    k = 0 if own.bundle is None else len(own.bundle)
    first = len(joined.bundle) - k
    if not joined.connected or k == 0 or first < 0 or len(np.unique(joined.bundle.drive[first:])) != 1:
        out["closures"] = []
        return out
    poses = joined.bundle.poses[first:]
    out["closures"] = [{**c, **{f"{end}_xy_m": [round(float(v), 4) for v in poses[c[end], :2]]
                                for end in ("node", "anchor")}} for c in loop_summary["closures"]]
    return out


def write_joined_products(joined: JoinedMap, config: SlamConfig, out_dir: str | Path, relations=None,
                          base_result: SlamResult | None = None, georef: Georeference | None = None
                          ) -> dict[str, Path]:
    """The products of a joint map in ``out_dir``: every product of a mapping run over all its connected
    drives (:func:`joined_result`), the new ``map_bundle.npz``, ``drives.png`` and, for an extension
    (``base_result``: the new drive's own run), its change map against the saved map (``changes.png``,
    ``changes.geojson``; ``georef`` places the GeoJSON on Earth)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    drawn = {"drives.png": save_png(drives_image(joined.grid, joined.trajectory, joined.trajectory_drive),
                                    out / "drives.png")}
    found = extension_changes(joined, config) if base_result is not None else None
    if found is not None:
        drawn.update(write_changes(out, *found, georef=georef))
    result = joined_result(joined, config, base_result, None if found is None else found[0])
    return {**drawn, **write_products(result, out, relations=relations, extra_products=sorted(drawn))}
