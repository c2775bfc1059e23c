"""``run.json``: what was run on what, how long it took, how the filter behaved, and how accurate it was.

Top-level keys: ``config`` (the SlamConfig used), ``input`` (the log's summary), ``timings``
(wall time, scans, scans/s, per-step time percentiles), ``memory`` (peak bytes), ``time_offset`` (the
LiDAR-to-odometry time offset: estimated, its standard error, applied; whether scans were de-skewed),
``filter`` (resamples,
match rate, N_eff, particle counts), ``map`` (size, resolution, origin, cell counts, ``consistency``: whether the map
contradicts its own scans), ``georeference``, ``accuracy``
(relation errors and/or ATE when relations / ground truth were given, ``texture`` colour error and
placement for a simulated log with a known floor; else null), ``warnings``,
``scan_stats`` (per processed scan, columnar: t_s, n_eff, resampled, match_score, matched,
step_time_s, particles) and ``products`` (the files written).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from slam_engine.model.result import SlamResult
from slam_engine.products.files import write_text_atomic
from slam_engine.products.rendering import OccupancyRasters, occupancy_rasters

FORMAT_NAME = "lidarmap-run"


def to_jsonable(value):
    """Plain JSON values from dataclasses, pydantic models, numpy arrays and scalars; NaN/inf -> None."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if hasattr(value, "model_dump"):
        return to_jsonable(value.model_dump(mode="json"))
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, np.generic):
        return to_jsonable(value.item())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Path):
        return str(value)
    return value


def build_run_report(result: SlamResult, input_summary: dict | None = None, georeference: dict | None = None,
                     accuracy: dict | None = None, products: list[str] | None = None,
                     rasters: OccupancyRasters | None = None) -> dict:
    """The run.json document (see module docstring); ``rasters``: the grid's rasters when already
    made (their cell counts)."""
    stats = result.scan_stats
    step = np.asarray(stats.step_time_s, dtype=np.float64)
    processed = int(step.size)
    wall = float(result.wall_time_s)
    scans = len(result.trajectory)
    counts = rasters if rasters is not None else occupancy_rasters(result.grid)
    h, w = result.grid.shape
    return to_jsonable({
        "format": FORMAT_NAME,
        "version": 1,
        "config": result.config,
        "input": input_summary if input_summary is not None else result.input_summary,
        "timings": {
            "wall_time_s": wall,
            "scans": scans,
            "scans_processed": processed,
            "scans_per_s": scans / wall if wall > 0 else None,
            "step_time_s": _percentiles(step),
        },
        "memory": {"peak_bytes": int(result.peak_memory_bytes)},
        # the back end: submaps, closures found, accepted and rejected (with why), each one's correction
        "loop_closing": result.input_summary.get("loop_closing"),
        # a scan stamped t was measured at t + offset on the odometry's clock (slam_engine.frontend.time_offset)
        "time_offset": result.input_summary.get("time_offset"),
        # an extension: what its drive saw changed since the saved map (slam_engine.multisession.changes)
        "changes": result.input_summary.get("changes"),
        "filter": {
            "resample_count": int(np.count_nonzero(stats.resampled)),
            "match_rate": float(np.mean(stats.matched)) if processed else None,
            "n_eff_mean": float(np.mean(stats.n_eff)) if processed else None,
            "n_eff_min": float(np.min(stats.n_eff)) if processed else None,
            # particles after each step: a fixed count, or KLD-sampling's between min_particles and particles
            "particles_median": float(np.median(stats.particles)) if stats.particles.size else None,
            "particles_min": int(np.min(stats.particles)) if stats.particles.size else None,
            "particles_max": int(np.max(stats.particles)) if stats.particles.size else None,
            "match_score_mean": float(np.mean(stats.match_score)) if processed else None,
        },
        "map": {
            "resolution_m": float(result.grid.resolution_m),
            "width_cells": int(w), "height_cells": int(h),
            "origin_m": [float(result.grid.origin_x_m), float(result.grid.origin_y_m)],
            "known_cells": counts.known_cells,
            "occupied_cells": counts.occupied_cells,
            "free_cells": counts.free_cells,
            "has_texture": result.texture is not None,
            "snapshots": len(result.snapshots),
            # whether the key frames' returns fall where the map holds free space (evaluation.consistency)
            "consistency": result.input_summary.get("map_consistency"),
        },
        "georeference": georeference,
        "accuracy": accuracy,
        "warnings": list(result.warnings),
        "scan_stats": {f.name: getattr(stats, f.name) for f in dataclasses.fields(stats)},
        "products": products or [],
    })


def _percentiles(values: np.ndarray) -> dict | None:
    if values.size == 0:
        return None
    p50, p95 = np.percentile(values, [50, 95])
    return {"mean": float(values.mean()), "p50": float(p50), "p95": float(p95), "max": float(values.max())}


def write_run_json(report: dict, path: str | Path) -> Path:
    """Write the report as indented JSON; returns the path."""
    return write_text_atomic(path, json.dumps(report, indent=1, allow_nan=False) + "\n")
