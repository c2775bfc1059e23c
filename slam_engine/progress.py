"""A run's progress in named stages, in order (:data:`STAGES`): the front end maps the scans, the back end
closes loops and aligns the key frames to the map, the product map is rendered, the caller writes the
products. :attr:`RunProgress.fraction` is the whole run's share done, each stage weighted by its usual
share of the time (:data:`STAGE_SHARES`). Imports nothing heavy: the service's API reads these too."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from slam_engine.model.result import MapSnapshot

MAPPING_SCANS = "mapping scans"
CLOSING_LOOPS = "closing loops"
ALIGNING_TO_MAP = "aligning to the map"
RENDERING_MAP = "rendering the map"
WRITING_PRODUCTS = "writing products"  # reported by the caller, around its product writing
# Each stage's share of a run's time, as measured on intel and aces-rough (2026-11-26: the front end 69-70 %,
# loop closing 23-24 %, the alignment 3-5 %, the map under 1 %, the products 2 %).
STAGE_SHARES = {MAPPING_SCANS: 0.70, CLOSING_LOOPS: 0.22, ALIGNING_TO_MAP: 0.04, RENDERING_MAP: 0.01,
                WRITING_PRODUCTS: 0.03}
STAGES = tuple(STAGE_SHARES)  # in the order a run goes through them


def run_fraction(stage: str, stage_fraction: float) -> float:
    """The whole run's share done [0..1] at ``stage_fraction`` (0..1) of ``stage``: 1.0 only at the end of
    the last stage."""
    index = STAGES.index(stage)
    part = min(1.0, max(0.0, stage_fraction))
    if index == len(STAGES) - 1 and part >= 1.0:
        return 1.0
    before = sum(STAGE_SHARES[s] for s in STAGES[:index])
    return min(1.0, before + STAGE_SHARES[stage] * part)


@dataclass(frozen=True)
class RunProgress:
    """Progress of a run: scans handled so far, scans in the log, seconds since the start, the newest
    map snapshot kept so far (``config.snapshot_every_scans``; None before the first), for live
    previews (its map pooled to at most about ``PREVIEW_MAX_SIDE_CELLS`` a side; older snapshots are
    pooled further, to an animation frame's size), the stage (one of :data:`STAGES`) and the share of
    it done (None: the scans' share, for :data:`MAPPING_SCANS`)."""

    scans_done: int
    scans_total: int
    elapsed_s: float
    latest_snapshot: MapSnapshot | None = None
    stage: str = MAPPING_SCANS
    stage_fraction: float | None = None

    @property
    def fraction(self) -> float:
        """The whole run's share done, 0..1 (:func:`run_fraction`)."""
        part = self.stage_fraction
        if part is None:
            part = self.scans_done / self.scans_total if self.scans_total else 0.0
        return run_fraction(self.stage, part)


def stage_progress(stage: str, scans_total: int, started_s: float, stage_fraction: float = 0.0) -> RunProgress:
    """A report of ``stage`` (after the scans were mapped), timed from ``started_s`` (``time.perf_counter()``)."""
    return RunProgress(scans_total, scans_total, time.perf_counter() - started_s, stage=stage,
                       stage_fraction=stage_fraction)


ProgressCallback = Callable[[RunProgress], None]
