"""A 2-D world: walls as line segments (rooms, corridors, buildings), a textured floor, and a route.

Walls are vertical and ``wall_height_m`` tall; the floor is the plane z = 0. Coordinates are the
world (ground-truth) frame in metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class World:
    """Walls ``segments`` (S, 4) [x0, y0, x1, y1] m; ``route`` (K, 2) waypoints of a closed drive."""

    name: str
    segments: np.ndarray
    route: np.ndarray
    wall_height_m: float
    cruise_speed_m_s: float
    tile_size_m: float = 0.6
    # what changed since the world this one is a later state of (``changed_from``): walls (S, 4) taken
    # away and put up; the truth a change map is scored against
    changed_from: str | None = None
    removed: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    added: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))

    def raycast(self, origin_xyz: np.ndarray, directions: np.ndarray, max_range_m: float) -> np.ndarray:
        """Ranges [m] along unit 3-D rays from one origin; ``inf`` where nothing is hit in range.

        ``origin_xyz`` (3,) world point, or (B, 3) one per ray (a scanner that moves during its
        sweep); ``directions`` (B, 3) unit vectors in the world frame. A ray stops at the first wall
        (if it meets it below the wall's top) or at the floor.
        """
        o = np.atleast_2d(np.asarray(origin_xyz, dtype=np.float64))  # (1 or B, 3)
        d = np.asarray(directions, dtype=np.float64)
        p = self.segments[:, :2]
        e = self.segments[:, 2:] - p  # (S, 2)
        # Solve o + t d_xy = p + u e per ray and segment; t is the 3-D range since d is unit length.
        denom = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # cross(d, e)  (B, S)
        w = p[None, :, :] - o[:, None, :2]  # (1 or B, S, 2)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (w[..., 0] * e[None, :, 1] - w[..., 1] * e[None, :, 0]) / denom
            u = (w[..., 0] * d[:, None, 1] - w[..., 1] * d[:, None, 0]) / denom
            hit_z = o[:, 2:3] + t * d[:, None, 2]
            valid = (np.abs(denom) > 1e-12) & (t > 1e-6) & (u >= 0.0) & (u <= 1.0)
            valid &= (hit_z >= 0.0) & (hit_z <= self.wall_height_m)
        t = np.where(valid, t, np.inf)
        wall = t.min(axis=1) if t.shape[1] else np.full(len(d), np.inf)
        with np.errstate(divide="ignore"):
            floor = np.where(d[:, 2] < -1e-9, o[:, 2] / -d[:, 2], np.inf)
        ranges = np.minimum(wall, floor)
        ranges[ranges > max_range_m] = np.inf
        return ranges

    def floor_rgb(self, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """(N, 3) uint8 floor colour at world points: tiles of a per-tile colour, dark grout lines
        and a fine speckle (2 cm) so that image matching has texture everywhere."""
        x = np.asarray(x_m, dtype=np.float64).ravel()
        y = np.asarray(y_m, dtype=np.float64).ravel()
        tile = self.tile_size_m
        tx, ty = np.floor(x / tile).astype(np.int64), np.floor(y / tile).astype(np.int64)
        base = _PALETTE[_hash2(tx, ty, 17) % len(_PALETTE)].astype(np.float64)
        fx, fy = x / tile - tx, y / tile - ty
        grout = (np.minimum(np.minimum(fx, 1 - fx), np.minimum(fy, 1 - fy)) * tile) < 0.015
        sx, sy = np.floor(x / 0.02).astype(np.int64), np.floor(y / 0.02).astype(np.int64)
        speckle = (_hash2(sx, sy, 101) % 61).astype(np.float64) - 30.0
        rgb = base + speckle[:, None]
        rgb[grout] = 45.0
        return np.clip(rgb, 0, 255).astype(np.uint8)


_PALETTE = np.array([[196, 170, 132], [160, 160, 150], [120, 138, 160], [186, 120, 96],
                     [140, 170, 120], [210, 200, 180], [100, 100, 110], [170, 150, 190]])


def _hash2(ix: np.ndarray, iy: np.ndarray, salt: int) -> np.ndarray:
    """Deterministic pseudo-random non-negative int64 per integer cell (a SplitMix-style mix)."""
    with np.errstate(over="ignore"):
        h = ix.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15) ^ iy.astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
        h ^= np.uint64(salt)
        h ^= h >> np.uint64(31)
        h *= np.uint64(0xBF58476D1CE4E5B9)
        h ^= h >> np.uint64(27)
    return (h >> np.uint64(33)).astype(np.int64)


def _wall(x0: float, y0: float, x1: float, y1: float, doors: tuple[tuple[float, float], ...] = ()) -> list:
    """Segments of a straight wall with door gaps; ``doors`` are (distance from start, width) [m]."""
    length = float(np.hypot(x1 - x0, y1 - y0))
    ux, uy = (x1 - x0) / length, (y1 - y0) / length
    cuts, start = [], 0.0
    for centre, width in sorted(doors):
        cuts.append((start, centre - width / 2))
        start = centre + width / 2
    cuts.append((start, length))
    return [[x0 + a * ux, y0 + a * uy, x0 + b * ux, y0 + b * uy] for a, b in cuts if b - a > 1e-9]


def _box(cx: float, cy: float, w: float, h: float, angle_rad: float = 0.0) -> list:
    """Four segments of a rectangle (furniture, pillar, building) centred at (cx, cy)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    corners = [(cx + c * dx - s * dy, cy + s * dx + c * dy)
               for dx, dy in ((-w / 2, -h / 2), (w / 2, -h / 2), (w / 2, h / 2), (-w / 2, h / 2))]
    return [[*corners[k], *corners[(k + 1) % 4]] for k in range(4)]


DOOR_M = 1.4  # the office's door width [m]
OFFICE_FURNITURE = ((2.0, 7.2, 2.4, 0.8, 0), (6.3, 3.6, 0.8, 0.8, 0.3), (11.0, 7.5, 1.6, 0.6, 0),
                    (13.5, 3.4, 1.2, 0.6, 0), (21.8, 7.0, 0.6, 1.8, 0), (18.2, 3.5, 0.5, 0.5, 0),
                    (1.6, -4.8, 1.2, 1.2, 0.5), (6.5, -1.2, 0.6, 0.6, 0), (10.5, -5.2, 2.0, 0.7, 0),
                    (14.2, -1.4, 0.8, 0.8, 0.8), (22.0, -4.0, 0.9, 2.2, 0), (18.0, -5.1, 1.0, 0.6, 0),
                    (11.0, 2.2, 0.3, 0.3, 0), (14.0, 0.2, 0.3, 0.3, 0), (8.0, 0.2, 0.3, 0.3, 0))


def _office_segments() -> list:
    segs: list = []
    segs += _wall(0, -6, 24, -6) + _wall(0, 8.4, 24, 8.4) + _wall(0, -6, 0, 8.4) + _wall(24, -6, 24, 8.4)
    segs += _wall(0, 2.4, 24, 2.4, ((4, DOOR_M), (20, DOOR_M)))  # corridor north wall
    segs += _wall(0, 0, 24, 0, ((4, DOOR_M), (20, DOOR_M)))  # corridor south wall
    for x in (8.0, 16.0):
        segs += _wall(x, 2.4, x, 8.4, ((3.0, DOOR_M),))  # between north rooms, door at y = 5.4
        segs += _wall(x, -6, x, 0, ((3.0, DOOR_M),))  # between south rooms, door at y = -3
    for box in OFFICE_FURNITURE:
        segs += _box(*box)
    return segs


def office() -> World:
    """A 24 m x 14.4 m office floor: an east-west corridor with three rooms on each side, doors
    between neighbouring rooms, furniture; the route runs through all six rooms and closes in the
    corridor and re-enters the first room the same way (about 57 m)."""
    route = np.array([(2.0, 1.2), (4.0, 1.2), (4.0, 3.4), (4.0, 5.4), (8.0, 5.4), (12.0, 5.4), (16.0, 5.4),
                      (20.0, 5.4), (20.0, 3.4), (20.0, 1.2), (20.0, -1.0), (20.0, -3.0), (16.0, -3.0),
                      (12.0, -3.0), (8.0, -3.0), (4.0, -3.0), (4.0, -1.0), (4.0, 1.2), (4.0, 3.4), (4.0, 5.4),
                      (7.0, 5.4)])
    return World("office", np.array(_office_segments(), dtype=np.float64), route, wall_height_m=2.6,
                 cruise_speed_m_s=0.6)


NORTH_ROUTE = ((2.0, 1.2), (4.0, 1.2), (4.0, 3.4), (4.0, 5.4), (8.0, 5.4), (12.0, 5.4), (16.0, 5.4), (20.0, 5.4),
               (20.0, 3.4), (20.0, 1.2), (16.0, 1.2), (12.0, 1.2), (8.0, 1.2), (4.0, 1.2), (4.0, 3.4), (4.0, 5.4),
               (6.0, 5.4))  # the north rooms and the corridor, never the south rooms (about 45 m)


def office_north() -> World:
    """The office driven through its north rooms and corridor only: a map of it has never seen the south
    rooms, which the office's own route drives through (a drive that leaves the map and comes back)."""
    return World("office-north", np.array(_office_segments(), dtype=np.float64), np.array(NORTH_ROUTE),
                 wall_height_m=2.6, cruise_speed_m_s=0.6)


def office_changed() -> World:
    """The office some days later: a desk moved 4 m (from the north-middle room's far wall to its
    corridor side), the pillar in the north-east room taken away, the corridor's south door to the
    south-east room closed, and a 2.6 m partition put up in the north-east room. The route keeps to
    the north rooms and the corridor (about 45 m), where every change is in sight."""
    desk, moved_desk, pillar = OFFICE_FURNITURE[2], (10.5, 3.7, 1.6, 0.6, 0), OFFICE_FURNITURE[5]
    removed = _box(*desk) + _box(*pillar)
    added = _box(*moved_desk) + [[20 - DOOR_M / 2, 0.0, 20 + DOOR_M / 2, 0.0], [22.8, 3.0, 22.8, 5.6]]
    segs = [s for s in _office_segments() if s not in removed] + added
    return World("office-changed", np.array(segs, dtype=np.float64), np.array(NORTH_ROUTE), wall_height_m=2.6,
                 cruise_speed_m_s=0.6,
                 changed_from="office", removed=np.array(removed, dtype=np.float64),
                 added=np.array(added, dtype=np.float64))


def campus() -> World:
    """Four city blocks (40 m x 30 m buildings, 12 m streets) inside a ring of facades, with kiosks
    and poles along the kerbs; the route drives the outer streets once around (about 300 m)."""
    segs: list = []
    for x0, x1 in ((0, 40), (52, 92)):
        for y0, y1 in ((0, 30), (42, 72)):
            segs += _box((x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0)
            segs += _box(x0 + 9, y0 - 0.6, 3.0, 1.2)  # a porch breaks the long facade
    segs += _box(46, 36, 116, 96)  # ring of facades 6 m beyond the outer street centres
    rng = np.random.default_rng(20240611)  # fixed: the world is part of the scenario, not the run
    for _ in range(40):
        side = rng.integers(4)
        along = rng.uniform(-8, 100)
        x, y = [(along, -10.8), (102.8, along * 0.8), (along, 82.8), (-10.8, along * 0.8)][side]
        segs += _box(x, y, rng.uniform(0.3, 2.5), rng.uniform(0.3, 1.5), rng.uniform(0, np.pi))
    route = np.array([(-6, -6), (98, -6), (98, 36), (-6, 36), (-6, -6), (30, -6)], dtype=np.float64)
    return World("campus", np.array(segs, dtype=np.float64), route, wall_height_m=15.0, cruise_speed_m_s=5.0,
                 tile_size_m=1.0)


SCENARIOS = {"office": office, "office-north": office_north, "office-changed": office_changed, "campus": campus}
