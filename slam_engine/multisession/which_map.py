"""Which of several saved maps a drive is in: the maps ordered by the place index, then the drive localised
in them in that order.

Each map's place index (:mod:`slam_engine.backend.place_index`: places along the path that made the map and
on a lattice over the free space it observed) is asked how much the drive looks like it: ``stretches``
stretches of ``stretch_m`` of travel spread over the drive, each one's best place similarity, their median
(0-1). The drive is then localised (:class:`~slam_engine.multisession.localization.Localizer`, confirmed
by a second stretch, as for one map) in the maps in that order; the first map it is
localised in is the answer and the maps after it are not searched. A drive localised in none is refused,
with every map's best score. The order only decides how soon the answer comes: every map that is tried is
judged by the same search as one map alone.

Frames: each map's own; the drive's scans in its own (odometry) frame.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass, field

import numpy as np

from slam_engine.backend.place_index import PlaceIndex, QueryDescription, describe_query
from slam_engine.config import SlamConfig
from slam_engine.errors import ConfigError
from slam_engine.model.drive_log import DriveLog
from slam_engine.model.map_bundle import MapBundle
from slam_engine.multisession.localization import (
    DriveScans,
    LocalizationResult,
    Localizer,
    MapIndex,
    MapPlaces,
    OwnLoops,
    map_places_of,
)

DESCRIBE_POINTS = 3000  # a stretch's end points that describe it to the index, at most


@dataclass
class MapTry:
    """One saved map as the drive met it: its ``name``, how much the drive looks like it (``likeness``,
    0-1), whether the drive was localised in it (None: not tried, an earlier map took it), the best
    placement score there and the seconds spent on it (its index and, when tried, localising)."""

    name: str
    likeness: float
    localised: bool | None = None
    best_score: float | None = None
    seconds: float = 0.0

    def as_dict(self) -> dict:
        return {"map": self.name, "likeness": round(self.likeness, 4), "localised": self.localised,
                "best_score": None if self.best_score is None else round(self.best_score, 4),
                "seconds": round(self.seconds, 3)}


@dataclass
class WhichMap:
    """The answer: ``chosen`` (index into ``tries``, None when refused everywhere), ``result`` (the
    localisation in the chosen map; None when refused), the drive's scans, and every map's try in the
    order they were tried."""

    chosen: int | None
    result: LocalizationResult | None
    drive: DriveScans
    tries: list[MapTry] = field(default_factory=list)
    wall_time_s: float = 0.0

    def refusal_reason(self, min_score: float, prefix: str = "") -> str:
        """Why the drive was placed in no map, in one line: each tried map's best score (named with
        ``prefix``) against ``min_score``."""
        scores = ", ".join(f"{prefix}{t.name}: {t.best_score:.3f}" for t in self.tries if t.best_score is not None)
        return f"best scores {scores}; {min_score:g} needed, unambiguous and confirmed"

    def summary(self) -> dict:
        return {"chosen": None if self.chosen is None else self.tries[self.chosen].name,
                "maps": [t.as_dict() for t in self.tries], "wall_time_s": round(self.wall_time_s, 3)}


def stretch_descriptions(drive: DriveScans, config: SlamConfig) -> list[QueryDescription]:
    """The drive as the maps' place indexes are asked about it: ``stretches`` stretches of ``stretch_m``
    spread over the drive, each described once (the same for every map)."""
    c = config.place_index
    ends = np.unique(np.linspace(0, len(drive) - 1, c.stretches + 1)[1:].round().astype(int))
    described = []
    for last in ends.tolist():
        first = int(np.searchsorted(drive.travel_m, drive.travel_m[last] - c.stretch_m))
        described.append(describe_query(drive.cloud(first, last, DESCRIBE_POINTS), c.radius_m))
    return described


def likeness(index: PlaceIndex, stretches: Sequence[QueryDescription]) -> float:
    """How much the drive looks like the map of ``index`` (0-1): the median over the drive's stretches
    (:func:`stretch_descriptions`) of the best place's similarity."""
    scores = []
    for described in stretches:
        found = index.query(described, 1)
        scores.append(found[0].similarity if found else 0.0)
    return float(np.median(scores)) if scores else 0.0


def localize_in_maps(maps: Sequence[tuple[str, MapBundle]], log: DriveLog, config: SlamConfig | None = None,
                     threads: int = 1) -> WhichMap:
    """The drive of ``log`` localised in the first of ``maps`` ((name, bundle) pairs) that places it, tried
    in the order of the drive's likeness to each (see the module docstring). With ``threads`` > 1 the
    drive's scans are matched in a second thread while this one makes the maps' places; a map's match
    grids are made only when the drive is tried in it."""
    if not maps:
        raise ConfigError("no saved map to localise in")
    config = SlamConfig() if config is None else config
    started = time.perf_counter()
    with ThreadPoolExecutor(1) if threads > 1 else nullcontext() as pool:
        matching = None if pool is None else pool.submit(DriveScans.from_log, log, config)
        made, seconds = [], []
        for _, bundle in maps:
            t0 = time.perf_counter()
            made.append(map_places_of(bundle, config.place_index))
            seconds.append(time.perf_counter() - t0)
        drive = DriveScans.from_log(log, config) if matching is None else matching.result()
    stretches = stretch_descriptions(drive, config)
    tries = []
    for (name, _), places, spent in zip(maps, made, seconds, strict=True):
        t0 = time.perf_counter()
        tries.append(MapTry(name, likeness(places, stretches), seconds=spent + time.perf_counter() - t0))
    order = sorted(range(len(maps)), key=lambda i: -tries[i].likeness)
    chosen, result = None, None
    for i in order:
        t0 = time.perf_counter()
        index = MapIndex.of_bundle(maps[i][1], config.localization)
        placed = Localizer(index, drive, config.localization, threads, OwnLoops.of(config),
                           MapPlaces.of_index(made[i], config)).run()
        tries[i].localised, tries[i].best_score = placed.localised, placed.best_score
        tries[i].seconds += time.perf_counter() - t0
        if placed.localised:
            chosen, result = i, placed
            break
    ordered = [tries[i] for i in order]
    return WhichMap(None if chosen is None else order.index(chosen), result, drive, ordered,
                    time.perf_counter() - started)
