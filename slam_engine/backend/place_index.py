"""A place index: which places of a map a cloud of end points may be at, and its heading there, without
searching the whole map.

A *place* is a point of the map where the vehicle was (world frame) and the map's end points within
``radius_m`` of it, binned on a polar grid of ``RINGS`` rings of equal width by ``SECTORS`` sectors,
world-aligned (sector 0 starts at +x), each bin occupied or not: a descriptor in the style of Scan Context
(Kim and Kim, IROS 2018), built from the map's points rather than one scan, so that a 180-degree
scanner's map still describes a full circle. A query (a stretch of a drive, in its last scan's vehicle
frame) is binned the same way and compared with every place at every sector shift (circular
cross-correlation along the sectors, one FFT per ring), scored by cosine similarity over the bins the
query saw (in each sector, out to a little beyond its farthest return: a place's walls behind the
query's are not held against it); each peak of the shifts is a heading in the world frame. Retrieval is
rotation-invariant and brute force: places x rings x sectors, the places' spectra read once for the nine
descriptions of a query (:func:`_ring_sums`): 80 ms for the campus's 5800 places (200 ms when each
description read them twice), a few ms for a building's.

The index proposes; it never accepts. :func:`search_at_places` searches for the best pose only around the
proposed places, on the whole-map search's lattice, and for a runner-up over the whole map: where the
index holds the place, the whole-map search's own verdict; where it misses it, ambiguous or too low,
never a wrong unique placement. Far loop searches (indoors) and localisation's searches over the whole
map use it that way; :mod:`slam_engine.multisession.which_map` orders several saved maps by how much a
drive looks like each. Recall@5 at the benchmark logs' true
revisits (``python -m bench.place_recall``, 2026-11-29): intel 0.93, aces-rough 1.0, the corridor 0.67,
the campus 0.85.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cached_property

import numba as nb
import numpy as np

from slam_engine.backend.correlative import (
    CorrelativeMatch,
    MatchGrid,
    lattice_pose,
    runner_up_among,
    runner_up_score,
    search,
)
from slam_engine.config import PlaceIndexConfig
from slam_engine.model.map_bundle import StoredPlaces
from slam_engine.model.poses import wrap_angle

RINGS, SECTORS = 20, 72  # polar bins: rings of radius_m / RINGS, sectors of 5 degrees
SECTOR_RAD = 2.0 * math.pi / SECTORS
# a bin's neighbours (one ring and one sector either side) count this much when it is empty: a query a
# little off the place's centre, or turned between two sectors, still overlaps it
NEIGHBOUR_WEIGHT = 0.5
MIN_BINS = 12  # a place or a query with fewer occupied bins describes nothing
# a query saw, in each sector, the rings out to its farthest return there and this many beyond (the
# place's map past them is out of its sight; recall@5 with 0 / 1 / 3: intel 0.92 / 0.92 / 0.93, the
# corridor 0.59 / 0.60 / 0.62, the campus 0.67 / 0.68 / 0.71 at a 12 m radius)
SEEN_BEYOND_RINGS = 3
BUCKETS_PER_RADIUS = 4  # binning places: the points bucketed on cells of a quarter of the radius
DEDUPE_CELL_M = 0.1  # points are kept once per cell of this size before binning (density does not count)
# candidates closer than this [m] (and turned less than SUPPRESS_RAD) to a better one are the same place
SUPPRESS_M, SUPPRESS_RAD = 3.0, 0.5
# a query is described from its vehicle and from these points around it [m, vehicle frame]: a place's
# centre is seldom where the vehicle is (recall@5 at the benchmark logs' revisits: intel 0.74 -> 0.83,
# aces-rough 0.69 -> 0.92; a 1.5 m or 2 m spread did no better)
QUERY_OFFSETS_M = tuple((dx, dy) for dx in (-1.0, 0.0, 1.0) for dy in (-1.0, 0.0, 1.0))


def describe(points_m: np.ndarray, centre_m: np.ndarray | tuple[float, float], radius_m: float) -> np.ndarray:
    """(RINGS, SECTORS) float32 descriptor of the points (N, 2) [m] around ``centre_m`` (2,), sectors
    measured from the points' +x axis: 1 where a bin holds a point, the neighbour weight where only a
    neighbouring bin does, else 0."""
    return _described(points_m, np.asarray(centre_m, np.float64)[None, :2], radius_m)[0]


@nb.njit(cache=True, nogil=True, parallel=True)
def _bin_points(points_m, order, bucket_starts, width, lo_x, lo_y, cell_m, reach, centres_m, radius_m, hit):
    """Marks in ``hit`` (P, RINGS, SECTORS) each bin of place p (centre ``centres_m[p]``) that a point within
    ``radius_m`` of it (not on it) falls in. The points are bucketed on square cells of ``cell_m`` from
    (``lo_x``, ``lo_y``), ``width`` a row: ``order[bucket_starts[b]:bucket_starts[b + 1]]`` are bucket b's; a
    place looks in the buckets up to ``reach`` (``reach * cell_m`` >= ``radius_m``) from its own that come
    within the radius. Places run in parallel threads (each writes only its own bins): the same bins as
    a serial loop."""
    two_pi = 2.0 * np.pi
    height = (bucket_starts.shape[0] - 1) // width
    for p in nb.prange(centres_m.shape[0]):
        cx, cy = centres_m[p, 0], centres_m[p, 1]
        bx = int(math.floor((cx - lo_x) / cell_m))
        by = int(math.floor((cy - lo_y) / cell_m))
        for ny in range(max(by - reach, 0), min(by + reach + 1, height)):
            gap_y = max(lo_y + ny * cell_m - cy, cy - (lo_y + (ny + 1) * cell_m), 0.0)
            for nx in range(max(bx - reach, 0), min(bx + reach + 1, width)):
                gap_x = max(lo_x + nx * cell_m - cx, cx - (lo_x + (nx + 1) * cell_m), 0.0)
                if gap_x * gap_x + gap_y * gap_y > radius_m * radius_m * (1.0 + 1e-9):
                    continue  # the bucket lies wholly beyond the radius
                b = ny * width + nx
                for j in range(bucket_starts[b], bucket_starts[b + 1]):
                    dx = points_m[order[j], 0] - cx
                    dy = points_m[order[j], 1] - cy
                    rng = math.hypot(dx, dy)
                    if not (rng < radius_m and rng > 1e-6):
                        continue
                    ring = min(int(rng / radius_m * RINGS), RINGS - 1)
                    bearing = math.atan2(dy, dx) % two_pi
                    sector = min(int(bearing / SECTOR_RAD), SECTORS - 1)
                    hit[p, ring, sector] = 1.0


def _described(points_m: np.ndarray, centres_m: np.ndarray, radius_m: float) -> np.ndarray:
    """(P, RINGS, SECTORS) float32: :func:`describe` of each centre (P, 2) with the points (N, 2) [m]."""
    points = np.ascontiguousarray(points_m, np.float64).reshape(-1, 2)
    centres = np.ascontiguousarray(centres_m, np.float64).reshape(-1, 2)
    hit = np.zeros((len(centres), RINGS, SECTORS), np.float32)
    if len(points) and len(centres):
        lo = points.min(axis=0)
        cell = float(radius_m) / BUCKETS_PER_RADIUS
        cells = np.floor((points - lo) / cell).astype(np.int64)
        width = int(cells[:, 0].max()) + 1
        key = cells[:, 1] * width + cells[:, 0]
        order = np.argsort(key, kind="stable")
        starts = np.searchsorted(key[order], np.arange((int(cells[:, 1].max()) + 1) * width + 1))
        _bin_points(points, order, starts, width, float(lo[0]), float(lo[1]), cell, BUCKETS_PER_RADIUS + 1, centres,
                    float(radius_m), hit)
    return _with_neighbours(hit)


def _with_neighbours(hit: np.ndarray) -> np.ndarray:
    """Binary bins (..., RINGS, SECTORS) with each empty bin next to an occupied one at NEIGHBOUR_WEIGHT
    (sectors wrap around; rings do not)."""
    near = np.maximum(np.roll(hit, 1, axis=-1), np.roll(hit, -1, axis=-1))
    near[..., 1:, :] = np.maximum(near[..., 1:, :], hit[..., :-1, :])
    near[..., :-1, :] = np.maximum(near[..., :-1, :], hit[..., 1:, :])
    return np.maximum(hit, NEIGHBOUR_WEIGHT * near).astype(np.float32)


def seen_bins(occupied: np.ndarray) -> np.ndarray:
    """(RINGS, SECTORS) float32 mask of the bins a query whose occupied bins are ``occupied`` (RINGS,
    SECTORS) saw: in each sector with a return, the rings out to the farthest one and SEEN_BEYOND_RINGS
    beyond."""
    any_return = np.asarray(occupied.any(axis=0), bool)
    farthest = RINGS - 1 - np.argmax(occupied[::-1], axis=0)
    rings = np.arange(RINGS)[:, None]
    return ((rings <= farthest[None, :] + SEEN_BEYOND_RINGS) & any_return[None, :]).astype(np.float32)


def _deduped(points_m: np.ndarray) -> np.ndarray:
    """One point per DEDUPE_CELL_M cell (the cell's first), so that dense walls near the vehicle do not
    cost more than far ones."""
    points = np.asarray(points_m, np.float64)
    if len(points) == 0:
        return np.zeros((0, 2))
    cells = np.floor(points / DEDUPE_CELL_M).astype(np.int64)
    cells -= cells.min(axis=0)
    keys = cells[:, 0] * (int(cells[:, 1].max()) + 1) + cells[:, 1]  # one integer per cell: a 1-D unique
    _, first = np.unique(keys, return_index=True)
    return points[np.sort(first)]


@dataclass(frozen=True)
class QueryDescription:
    """End points (vehicle frame) described as a query: one descriptor per QUERY_OFFSETS_M (Q, RINGS,
    SECTORS), within ``radius_m``: the same for every index of that radius (several maps asked at once)."""

    descriptors: np.ndarray
    radius_m: float


def describe_query(points_v: np.ndarray, radius_m: float) -> QueryDescription:
    """The query description of end points ``points_v`` (N, 2) [m, vehicle frame] (:meth:`PlaceIndex.query`)."""
    points = _deduped(points_v)
    return QueryDescription(np.stack([describe(points, offset, radius_m) for offset in QUERY_OFFSETS_M]), radius_m)


@dataclass(frozen=True)
class PlaceCandidate:
    """A place a query may be at: its index, centre (2,) [m, world], the query's heading there [rad,
    world] and the descriptors' similarity (0-1)."""

    place: int
    centre_m: np.ndarray
    heading_rad: float
    similarity: float


@dataclass(frozen=True)
class PlaceIndex:
    """Places of a map: ``centres`` (P, 2) [m, world frame], their ``descriptors`` (P, RINGS, SECTORS)
    and the radius they describe [m]."""

    centres: np.ndarray
    descriptors: np.ndarray
    radius_m: float

    def __len__(self) -> int:
        return len(self.centres)

    @classmethod
    def build(cls, points_m: np.ndarray, centres_m: np.ndarray, radius_m: float) -> PlaceIndex:
        """The places at ``centres_m`` (P, 2) of the map whose end points are ``points_m`` (N, 2) [m,
        world]; places that describe too little (fewer than MIN_BINS occupied bins) are left out."""
        points = _deduped(points_m)
        centres = np.asarray(centres_m, np.float64).reshape(-1, 2)
        if len(points) == 0 or len(centres) == 0:
            return cls(np.zeros((0, 2)), np.zeros((0, RINGS, SECTORS), np.float32), radius_m)
        descriptors = _described(points, centres, radius_m)
        keep = (descriptors == 1.0).sum(axis=(1, 2)) >= MIN_BINS
        return cls(centres[keep], descriptors[keep], radius_m)

    @classmethod
    def of_stored(cls, stored: StoredPlaces) -> PlaceIndex:
        """The index a map bundle keeps (:meth:`stored`)."""
        bins = np.asarray(stored.bins, bool)
        if bins.shape[1:] != (RINGS, SECTORS):
            raise ValueError(f"stored places of {bins.shape[1:]} bins; this index has {(RINGS, SECTORS)}")
        return cls(np.asarray(stored.centres, np.float64).reshape(-1, 2), _with_neighbours(bins.astype(np.float32)),
                   float(stored.radius_m))

    def stored(self, spacing_m: float) -> StoredPlaces:
        """The index as a map bundle keeps it: the occupied bins (the neighbours' weights follow from them)."""
        return StoredPlaces(self.centres.copy(), self.descriptors == 1.0, self.radius_m, float(spacing_m))

    @classmethod
    def along(cls, points_m: np.ndarray, positions_m: np.ndarray, spacing_m: float, radius_m: float) -> PlaceIndex:
        """:meth:`build` with a place every ``spacing_m`` of travel along ``positions_m`` (K, 2) [m] (the
        vehicle's path: where a query's vehicle may be)."""
        positions = np.asarray(positions_m, np.float64).reshape(-1, 2)
        return cls.build(points_m, positions[spaced(positions, spacing_m)], radius_m)

    @cached_property
    def _spectra(self) -> tuple[np.ndarray, np.ndarray]:
        """The places' FFTs along the sectors, of the descriptors and of their squares (each (P, RINGS,
        SECTORS // 2 + 1)); computed once, on the first query."""
        return np.fft.rfft(self.descriptors, axis=-1), np.fft.rfft(self.descriptors ** 2, axis=-1)

    def query(self, points_v: np.ndarray | QueryDescription, k: int) -> list[PlaceCandidate]:
        """The ``k`` places most like the end points ``points_v`` (N, 2) [m, vehicle frame] (or their
        :func:`describe_query`, to ask several indexes), best first, at most one per SUPPRESS_M /
        SUPPRESS_RAD; empty when the points describe too little or the index holds no place. The points
        are described from the vehicle and from QUERY_OFFSETS_M around it (a place's centre is seldom
        where the vehicle is); a candidate's centre is then where the vehicle is when that description
        matches (the place's centre less the offset, turned)."""
        if len(self) == 0 or k <= 0:
            return []
        described = points_v if isinstance(points_v, QueryDescription) else describe_query(points_v, self.radius_m)
        if described.radius_m != self.radius_m:
            raise ValueError(f"a query described within {described.radius_m} m asked of places of {self.radius_m} m")
        asked = []  # (offset, its descriptor over the bins it saw, those bins)
        for offset, q in zip(QUERY_OFFSETS_M, described.descriptors, strict=True):
            occupied = q == 1.0
            if int(occupied.sum()) >= MIN_BINS:
                seen = seen_bins(occupied)
                asked.append((offset, q * seen, seen))
        if not asked:
            return []
        # numerator[o, p, s] = sum over rings and query sectors j of q_o[r, j] * c[p, r, (j + s) % SECTORS]; masked:
        # the place's energy over the bins description o saw, turned the same way. One pass over the places'
        # spectra for every description (they are read once, not twice for each)
        C, C_squared = self._spectra
        numerator_f, masked_f = _ring_sums(C, C_squared, np.conj(np.fft.rfft(np.stack([a[1] for a in asked]), axis=-1)),
                                           np.conj(np.fft.rfft(np.stack([a[2] for a in asked]), axis=-1)))
        numerator = np.fft.irfft(numerator_f, n=SECTORS, axis=-1)
        masked = np.fft.irfft(masked_f, n=SECTORS, axis=-1)
        found = []
        for o, (offset, q, _) in enumerate(asked):
            places, heading, scores = _peaks(numerator[o], masked[o], float((q * q).sum()))
            cos, sin = np.cos(heading), np.sin(heading)
            vehicle = self.centres[places] - np.stack([cos * offset[0] - sin * offset[1],
                                                       sin * offset[0] + cos * offset[1]], axis=1)
            found.append((places, vehicle, heading, scores))
        places, vehicle, heading, scores = (np.concatenate(parts) for parts in zip(*found, strict=True))
        out: list[PlaceCandidate] = []
        for i in best_first(scores):
            centre, theta = vehicle[i], float(heading[i])
            if any(math.hypot(*(centre - c.centre_m)) < SUPPRESS_M
                   and abs(float(wrap_angle(theta - c.heading_rad))) < SUPPRESS_RAD for c in out):
                continue
            out.append(PlaceCandidate(int(places[i]), centre.copy(), theta, float(min(1.0, scores[i]))))
            if len(out) == k:
                break
        return out


@nb.njit(cache=True, nogil=True)
def _ring_sums(C, C_squared, Q, S):
    """(numerator, masked), each (O, P, F) complex: for every description o and place p, the sums over the
    rings r of ``Q[o, r] * C[p, r]`` and of ``S[o, r] * C_squared[p, r]`` (``C``, ``C_squared``: (P, R, F) the
    places' spectra and their squares'; ``Q``, ``S``: (O, R, F) the conjugate spectra of the descriptions over
    the bins they saw and of those bins), added ring after ring."""
    n_o, n_r, n_f = Q.shape
    n_p = C.shape[0]
    numerator = np.empty((n_o, n_p, n_f), C.dtype)
    masked = np.empty((n_o, n_p, n_f), C.dtype)
    for p in range(n_p):
        for o in range(n_o):
            for f in range(n_f):
                numerator[o, p, f] = Q[o, 0, f] * C[p, 0, f]
                masked[o, p, f] = S[o, 0, f] * C_squared[p, 0, f]
        for r in range(1, n_r):
            for o in range(n_o):
                for f in range(n_f):
                    numerator[o, p, f] += Q[o, r, f] * C[p, r, f]
                    masked[o, p, f] += S[o, r, f] * C_squared[p, r, f]
    return numerator, masked


def _peaks(numerator: np.ndarray, masked: np.ndarray, q_energy: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(place, heading [rad, world], similarity) of every local peak of each place's similarity with a query
    description over the sector shifts, from its cross-correlation ``numerator`` (P, SECTORS) with the
    places, the places' energy over the bins it saw ``masked`` (P, SECTORS) and its own ``q_energy``."""
    similarity = numerator / np.sqrt(q_energy * np.maximum(masked, 1e-9))
    # every heading that is a local peak of its place's profile is a candidate: corridors and
    # rectilinear rooms look alike turned by a half or a quarter turn, and only the search can tell
    left, right = np.roll(similarity, 1, axis=1), np.roll(similarity, -1, axis=1)
    places, shifts = np.nonzero((similarity >= left) & (similarity > right))
    scores = similarity[places, shifts]
    # the heading: the peak's shift refined by a parabola through its neighbours (sub-sector)
    lo, hi = left[places, shifts], right[places, shifts]
    curvature = lo - 2.0 * scores + hi
    safe = np.where(curvature < -1e-9, curvature, -1.0)
    offset = np.where(curvature < -1e-9, 0.5 * (lo - hi) / safe, 0.0)
    heading = np.asarray(wrap_angle((shifts + np.clip(offset, -0.5, 0.5)) * SECTOR_RAD))
    return places, heading, scores


def best_first(scores: np.ndarray, block: int = 256) -> Iterator[int]:
    """Indices of ``scores`` (N,), highest first, equal ones in index order: ``np.argsort(-scores,
    kind="stable")``, sorted a block at a time as they are taken (a query takes the first few of some
    hundred thousand peaks)."""
    remaining = np.arange(len(scores))
    negated = -np.asarray(scores)
    while len(remaining) > block:
        values = negated[remaining]
        kth = np.partition(values, block - 1)[block - 1]
        taken = values <= kth  # the block's best and every one tied with its last: none left behind beats them
        chosen = remaining[taken]
        yield from chosen[np.argsort(negated[chosen], kind="stable")].tolist()
        remaining = remaining[~taken]
    yield from remaining[np.argsort(negated[remaining], kind="stable")].tolist()


def map_places(points_m: np.ndarray, path_m: np.ndarray, covers: Callable[[np.ndarray], np.ndarray],
               config: PlaceIndexConfig) -> PlaceIndex:
    """The places of a saved map whose end points are ``points_m`` (N, 2) [m, map frame]: every
    ``spacing_m`` along ``path_m`` (K, 2), the key frames that made it, and on a lattice over the free
    space it observed (``covers``: :func:`free_lattice`)."""
    path = np.asarray(path_m, np.float64).reshape(-1, 2)
    points = _deduped(points_m)
    centres = np.concatenate([path[spaced(path, config.spacing_m)], free_lattice(points, config.spacing_m, covers)])
    return PlaceIndex.build(points, centres, config.radius_m)


def free_lattice(points_m: np.ndarray, spacing_m: float, covers: Callable[[np.ndarray], np.ndarray],
                 clearance_m: float = 0.3) -> np.ndarray:
    """(P, 2) [m] points of a square lattice of ``spacing_m`` over the bounding box of ``points_m``
    (N, 2) where a vehicle may stand: on cells the map observed (``covers``: (P, 2) -> (P,) bool) and
    at least ``clearance_m`` from every end point. A saved map's places: a drive localised in it
    need not follow the path that made it."""
    points = np.asarray(points_m, np.float64)
    if len(points) == 0:
        return np.zeros((0, 2))
    lo, hi = points.min(axis=0), points.max(axis=0)
    xs = np.arange(lo[0] + spacing_m / 2, hi[0], spacing_m)
    ys = np.arange(lo[1] + spacing_m / 2, hi[1], spacing_m)
    lattice = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    if len(lattice) == 0:
        return lattice
    lattice = lattice[covers(lattice)]
    from scipy.spatial import cKDTree

    clear = cKDTree(points).query(lattice, distance_upper_bound=clearance_m)[0] > clearance_m
    return lattice[clear]


def spaced(positions_m: np.ndarray, spacing_m: float) -> np.ndarray:
    """Indices of ``positions_m`` (K, 2) [m] one every ``spacing_m`` of travel along them (the first
    always)."""
    if len(positions_m) == 0:
        return np.zeros(0, np.int64)
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(positions_m, axis=0).T))])
    picks, next_m = [], 0.0
    for i, t in enumerate(travel.tolist()):
        if t >= next_m:
            picks.append(i)
            next_m = t + spacing_m
    return np.asarray(picks, np.int64)


def search_at_places(grid: MatchGrid, points_v: np.ndarray, initial_pose: np.ndarray, window_m: float,
                     window_rad: float, candidates: list[PlaceCandidate], place_window_m: float,
                     place_window_rad: float, min_score: float, ambiguity_m: float, ambiguity_rad: float,
                     runner_up_share: float, runner_up_min_score: float, runner_up_from: float = 0.0,
                     threads: int = 1, origins: np.ndarray | None = None) -> CorrelativeMatch | None:
    """:func:`~slam_engine.backend.correlative.search` over the wide window (``any_runner_up``), its best
    pose searched for only within ``place_window_m`` / ``place_window_rad`` of each candidate, on the wide
    search's lattice (every pose scores as it would there); the runner-up is then searched for over the
    whole wide window, as the wide search does.

    Where the wide search's best pose lies in a candidate's window, the answer is the wide search's. Where
    it does not (the index missed it), the best found is worse than it, and the runner-up search finds it:
    the match is ambiguous, or, below ``min_score``, not found. A miss of the index costs a placement,
    never a wrong one; a search that finds nothing near any candidate costs the small windows only. Where
    another candidate's window holds a pose that search would count (:func:`runner_up_among`), the match is
    ambiguous without it (on infinite-corridor-rough 19 of its 23 far searches' runner-ups, 0.5 s)."""
    matches = []
    for candidate in candidates:
        centre = lattice_pose(points_v, grid.resolution_m, initial_pose,
                              np.array([candidate.centre_m[0], candidate.centre_m[1], candidate.heading_rad]))
        match = search(grid, points_v, centre, place_window_m, place_window_rad, min_score, threads=threads,
                       origins=origins)
        if match is not None:
            matches.append(match)
    if not matches:
        return None
    best = max(matches, key=lambda m: m.score)  # the first of the best
    if best.score < runner_up_from:
        return CorrelativeMatch(best.pose, best.score, math.nan)
    floor = max(runner_up_min_score, runner_up_share * best.score)
    # another proposed place that scores as well already makes the best ambiguous: no whole-map search
    runner_up = runner_up_among(grid, points_v, initial_pose, window_m, window_rad, best.pose, floor, ambiguity_m,
                                ambiguity_rad, [m for m in matches if m is not best])
    if runner_up is None:
        runner_up = runner_up_score(grid, points_v, initial_pose, window_m, window_rad, best.pose, floor, ambiguity_m,
                                    ambiguity_rad, threads, origins)
    return CorrelativeMatch(best.pose, best.score, runner_up)
