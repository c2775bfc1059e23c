"""Office floors made up from a number: many buildings, each its own, for tests and benchmarks that need more
than one (which of ten saved maps a drive is in).

``building(n)`` is a floor of 16-26 m by 11-19 m: a corridor along x with rooms on both sides, each side cut
into rooms of its own widths (the two sides' walls do not line up), each room joined to the next by a door
in the wall between them, the first and last room on each side by a door to the corridor, furniture in the
rooms and pillars along the corridor. Its route drives into the first north room, through every north room,
back along the corridor, through every south room the other way, and into the first north room again
(a loop, closed where it began). ``building(n, back=True)`` is the same floor driven the other way round:
a second drive of a building, seen with the other heading at every place.

Scenario names (:func:`scenario_world`): ``building-N`` and ``building-N-back``, N from 1 to
``MAX_BUILDING``. The same number is always the same floor (its random draws are seeded by it).
Coordinates: the building's world frame [m], the corridor's south wall on y = 0 from x = 0.
"""

from __future__ import annotations

import re

import numpy as np

from slam_engine.simulation.world import DOOR_M, World, _box, _wall

MAX_BUILDING = 99
BUILDING_NAME = re.compile(r"^building-([1-9][0-9]?)(-back)?$")
SEED_SALT = 7_919  # a building's draws are seeded by SEED_SALT + its number
ROOM_WIDTH_M = (3.5, 6.5)  # a room's width along the corridor [m]
ROOM_DEPTH_M = (4.5, 7.5)  # a side's depth across the corridor [m]
CORRIDOR_M = (1.8, 3.0)  # the corridor's width [m]
CLEAR_OF_ROUTE_M = 0.8  # furniture and pillars stay this far [m] from the route (the robot is 0.4 m wide)
PILLAR_CLEAR_M = 0.45  # ... pillars against the corridor's walls, this far
CLEAR_OF_WALLS_M = 0.25  # furniture stays this far [m] from a room's walls
MIN_LEG_M = 1.5  # waypoints closer than this [m] are moved apart or merged (rounded corners need room)


def scenario_world(name: str) -> World | None:
    """The world of a ``building-N`` or ``building-N-back`` scenario; None for any other name."""
    found = BUILDING_NAME.match(name)
    if found is None:
        return None
    return building(int(found.group(1)), back=found.group(2) is not None)


def building(number: int, back: bool = False) -> World:
    """Office floor ``number`` (1..MAX_BUILDING; module docstring), driven forward or, with ``back``, the other
    way round."""
    if not 1 <= number <= MAX_BUILDING:
        raise ValueError(f"building number {number} is not within 1..{MAX_BUILDING}")
    rng = np.random.default_rng(SEED_SALT + number)
    length = float(rng.uniform(16.0, 26.0))
    corridor = float(rng.uniform(*CORRIDOR_M))
    north_depth, south_depth = (float(rng.uniform(*ROOM_DEPTH_M)) for _ in range(2))
    north = _room_walls(rng, length)
    south = _room_walls(rng, length)
    centre_y = corridor / 2
    north_y = corridor + north_depth * float(rng.uniform(0.4, 0.6))  # the line the route drives the rooms on
    south_y = -south_depth * float(rng.uniform(0.4, 0.6))
    north_doors = _corridor_doors(rng, north)
    south_doors = _south_doors(rng, south, north_doors)

    segs: list = []
    top, bottom = corridor + north_depth, -south_depth
    segs += _wall(0, bottom, length, bottom) + _wall(0, top, length, top)
    segs += _wall(0, bottom, 0, top) + _wall(length, bottom, length, top)
    segs += _wall(0, corridor, length, corridor, tuple((x, DOOR_M) for x in north_doors))
    segs += _wall(0, 0, length, 0, tuple((x, DOOR_M) for x in south_doors))
    for x in north[1:-1]:  # between the north rooms: a door on the route's line
        segs += _wall(x, corridor, x, top, ((north_y - corridor, DOOR_M),))
    for x in south[1:-1]:
        segs += _wall(x, bottom, x, 0, ((south_y - bottom, DOOR_M),))

    route = [(0.8, centre_y), (north_doors[0], centre_y), (north_doors[0], north_y), (north_doors[1], north_y),
             (north_doors[1], centre_y), (south_doors[1], centre_y), (south_doors[1], south_y),
             (south_doors[0], south_y), (south_doors[0], centre_y), (north_doors[0], centre_y),
             (north_doors[0], north_y), (north_doors[0] + 2.0, north_y)]
    route = _merged(route)
    segs += _furniture(rng, route, [(north[i], north[i + 1], corridor, top) for i in range(len(north) - 1)]
                       + [(south[i], south[i + 1], bottom, 0.0) for i in range(len(south) - 1)])
    segs += _pillars(rng, route, length, corridor)
    waypoints = np.array(route[::-1] if back else route, dtype=np.float64)
    return World(f"building-{number}" + ("-back" if back else ""), np.array(segs, dtype=np.float64), waypoints,
                 wall_height_m=2.6, cruise_speed_m_s=0.6)


def _room_walls(rng: np.random.Generator, length: float) -> list[float]:
    """x of a side's walls from 0 to ``length``: rooms of ROOM_WIDTH_M (the last one takes the rest)."""
    walls = [0.0]
    while length - walls[-1] > 2 * ROOM_WIDTH_M[0]:
        walls.append(walls[-1] + float(rng.uniform(ROOM_WIDTH_M[0], min(ROOM_WIDTH_M[1], length - walls[-1]
                                                                        - ROOM_WIDTH_M[0]))))
    walls.append(length)
    return walls


def _corridor_doors(rng: np.random.Generator, walls: list[float]) -> tuple[float, float]:
    """x of the corridor doors of a side's first and last room (1.2 m at least from the room's walls)."""
    first = float(rng.uniform(walls[0] + 1.2, walls[1] - 1.2))
    last = float(rng.uniform(walls[-2] + 1.2, walls[-1] - 1.2))
    return first, last


def _south_doors(rng: np.random.Generator, walls: list[float], north: tuple[float, float]) -> tuple[float, float]:
    """The south side's corridor doors, each at least MIN_LEG_M along the corridor from the north door at its
    end of the floor, or straight across from it where the room leaves no such place (the route turns
    between them)."""
    doors = []
    for room, across in ((0, north[0]), (len(walls) - 2, north[1])):
        lo, hi = walls[room] + 1.2, walls[room + 1] - 1.2
        apart = [x for x in rng.uniform(lo, hi, 50).tolist() if abs(x - across) >= MIN_LEG_M]
        doors.append(apart[0] if apart else across if lo <= across <= hi else float(rng.uniform(lo, hi)))
    return doors[0], doors[1]


def _merged(route: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The route without repeated waypoints or waypoints on a straight line between their neighbours."""
    out: list[tuple[float, float]] = []
    for point in route:
        if out and np.hypot(point[0] - out[-1][0], point[1] - out[-1][1]) < 1e-9:
            continue
        if len(out) >= 2:
            a, b = np.subtract(out[-1], out[-2]), np.subtract(point, out[-1])
            if abs(a[0] * b[1] - a[1] * b[0]) < 1e-9 and float(a @ b) > 0:
                out[-1] = point
                continue
        out.append(point)
    return out


def _distance_to_route(points: np.ndarray, route: list[tuple[float, float]]) -> np.ndarray:
    """(N,) distance [m] of each point (N, 2) to the route's legs."""
    p = np.asarray(points, np.float64).reshape(-1, 2)
    best = np.full(len(p), np.inf)
    for a, b in zip(route[:-1], route[1:], strict=True):
        a_, d = np.asarray(a), np.subtract(b, a)
        t = np.clip(((p - a_) @ d) / float(d @ d), 0.0, 1.0)
        best = np.minimum(best, np.hypot(*(p - (a_ + t[:, None] * d)).T))
    return best


def _box_clear(route: list[tuple[float, float]], cx: float, cy: float, w: float, h: float, angle: float,
               clear_m: float = CLEAR_OF_ROUTE_M) -> bool:
    """Whether a box keeps ``clear_m`` from the route (its outline sampled along each side)."""
    outline = np.array(_box(cx, cy, w, h, angle))
    samples = np.concatenate([np.linspace(s[:2], s[2:], 8) for s in outline])
    return bool(np.all(_distance_to_route(samples, route) >= clear_m))


def _furniture(rng: np.random.Generator, route: list[tuple[float, float]],
               rooms: list[tuple[float, float, float, float]]) -> list:
    """One to three desks, cupboards or tables per room (x0, x1, y0, y1), clear of its walls and the route."""
    segs: list = []
    for x0, x1, y0, y1 in rooms:
        wanted, placed = int(rng.integers(1, 4)), 0
        for _ in range(40):
            if placed == wanted:
                break
            w, h = float(rng.uniform(0.4, 2.2)), float(rng.uniform(0.4, 1.0))
            angle = float(rng.choice([0.0, np.pi / 2, rng.uniform(0, np.pi)]))
            reach = 0.5 * np.hypot(w, h) + CLEAR_OF_WALLS_M
            if x1 - x0 <= 2 * reach or y1 - y0 <= 2 * reach:
                continue
            cx, cy = float(rng.uniform(x0 + reach, x1 - reach)), float(rng.uniform(y0 + reach, y1 - reach))
            if _box_clear(route, cx, cy, w, h, angle):
                segs += _box(cx, cy, w, h, angle)
                placed += 1
    return segs


def _pillars(rng: np.random.Generator, route: list[tuple[float, float]], length: float, corridor: float) -> list:
    """Two to four square pillars or shelves against the corridor's walls, clear of the route."""
    segs: list = []
    for _ in range(int(rng.integers(2, 5))):
        size = float(rng.uniform(0.25, 0.5))
        x = float(rng.uniform(1.0, length - 1.0))
        y = size / 2 + 0.05 if rng.random() < 0.5 else corridor - size / 2 - 0.05
        if _box_clear(route, x, y, size, size, 0.0, PILLAR_CLEAR_M):
            segs += _box(x, y, size, size)
    return segs
