"""The engine's numba kernels: compiling them ahead of the first run, and noticing when they compile.

The kernels are compiled with ``cache=True``: numba keeps the machine code on disk (beside the
sources in ``__pycache__``, or under ``NUMBA_CACHE_DIR`` when that is set) and a later process loads
it instead of compiling (about 30 s on a 2-core machine). :func:`warm_up` fills that cache by mapping
a tiny simulated drive; ``python -m slam_engine.kernels`` runs it (the set-up script and the Docker
build do), prints which kernels it compiled and which it loaded, and exits non-zero if a kernel
still has to compile after it (``--check``: for a second process, that nothing compiled).

:func:`compile_notices` tells a caller (the service's job status) while a kernel compiles.
A cache is valid for the source files it was made from and this machine's CPU: an edited kernel or
a different CPU compiles again, once.
"""

from __future__ import annotations

import contextlib
import importlib
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any

KERNEL_MODULES = ("slam_engine.frontend.grid", "slam_engine.frontend.map_pooling", "slam_engine.frontend.raycast",
                  "slam_engine.frontend.scan_matcher", "slam_engine.backend.correlative", "slam_engine.backend.submaps",
                  "slam_engine.backend.polygon_fill", "slam_engine.backend.travel_graph",
                  "slam_engine.backend.place_index", "slam_engine.multisession.changes")
# Kernels a run calls from Python (the others are compiled into these).
ENTRY_KERNELS = ("grid._privatize", "grid._tiles_to_grid", "map_pooling.pool_known_max",
                 "raycast.collect_touched_tiles", "raycast.integrate_rays", "raycast._integrate_particle",
                 "raycast.clear_marks", "scan_matcher.match_particles", "scan_matcher.score_particles",
                 "correlative._rotated_cells", "correlative.branch_and_bound", "correlative._refine",
                 "correlative._refine_many", "submaps._blurred_hits", "polygon_fill.fill_polygons",
                 "travel_graph.shortest_distances", "place_index._bin_points", "place_index._ring_sums",
                 "changes._count_rays")


def kernels() -> dict[str, Any]:
    """Every numba dispatcher defined in the engine's kernel modules, by ``module.function``."""
    from numba.core.registry import CPUDispatcher

    found: dict[str, Any] = {}
    for module_name in KERNEL_MODULES:
        module = importlib.import_module(module_name)
        for name, obj in vars(module).items():
            if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == module_name:
                found[f"{module_name.rsplit('.', 1)[1]}.{name}"] = obj
    return found


def compile_report() -> dict[str, list[str]]:
    """What this process did with each kernel so far: ``compiled`` (no usable cache entry),
    ``loaded`` (from numba's on-disk cache)."""
    report: dict[str, list[str]] = {"compiled": [], "loaded": []}
    for name, dispatcher in sorted(kernels().items()):
        stats = dispatcher.stats
        if sum(stats.cache_misses.values()):
            report["compiled"].append(name)
        if sum(stats.cache_hits.values()):
            report["loaded"].append(name)
    return report


def warm_up() -> dict[str, list[str]]:
    """Run every entry kernel once (a tiny simulated drive through the filter, and a match that
    fails on an empty map), loading each from numba's cache or compiling it into the cache.
    Returns :func:`compile_report`."""
    import numpy as np

    from slam_engine.config import SlamConfig
    from slam_engine.frontend.grid import ParticleGrids
    from slam_engine.frontend.scan_matcher import ScanMatcher
    from slam_engine.model.result import OccupancyGrid
    from slam_engine.pipeline import run_slam
    from slam_engine.simulation import simulate

    drive = simulate("office", seed=0, rig="robot", max_duration_s=6.0)
    run_slam(drive.log, SlamConfig(particles=3, seed=0))
    OccupancyGrid(np.zeros((3, 3), np.float32), 0.05, 0.0, 0.0).pooled(2)  # snapshots and products
    # unknown cells score 0.5, below a min_score of 1: the match is rejected and the prediction
    # scored instead (score_particles)
    ScanMatcher(0.3, 0.2, 1.0).match(ParticleGrids(1, 0.05), np.zeros(1, np.int64), np.zeros((1, 3)),
                                     np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]))
    # the back end's matcher (a short drive closes no loop): a wall seen twice
    from slam_engine.backend.correlative import refine_pose, refine_poses, search
    from slam_engine.backend.submaps import match_grid_from_points, observed_mask

    wall = np.stack([np.linspace(0.0, 4.0, 80), np.full(80, 2.0)], axis=1)
    observed_mask([(np.array([2.0, 0.0]), wall)], np.array([-1.0, -1.0]), (80, 120), 0.05)
    match = search(match_grid_from_points(wall, 0.05, 1.0), wall, np.zeros(3), 0.5, 0.1, 0.1, ambiguity_m=0.5,
                   ambiguity_rad=0.1, runner_up_share=0.9)
    if match is not None:
        refine_pose(match_grid_from_points(wall, 0.05, 1.0), wall, match.pose)
    refine_poses(match_grid_from_points(wall, 0.05, 1.0), wall, np.array([0, 40, 80]), np.zeros((2, 3)),
                 np.array([0, 1]), first=1, step=2)  # the map alignment's fits, key frames in threads
    from slam_engine.backend.travel_graph import adjacency, shortest_distances

    shortest_distances(*adjacency(3, np.array([0, 1]), np.array([1, 2]), np.array([1.0, 1.0])), 0, 10.0)
    from slam_engine.backend.place_index import PlaceIndex

    # the place index: places binned, and a query (a localisation's or a far search's first)
    PlaceIndex.build(wall, np.array([[2.0, 0.0], [2.0, 4.0]]), 16.0).query(wall - [2.0, 0.0], 1)
    from slam_engine.multisession.changes import detect_changes

    detect_changes(OccupancyGrid(np.full((40, 40), -1.0, np.float32), 0.05, 0.0, 0.0), [wall[:5] - 1.0],
                   np.array([[1.0, 1.0, 0.0]]), np.zeros(2))  # a localisation's change map
    return compile_report()


class _CompileCounter:
    """A numba event listener: calls ``on_change(True)`` when the first kernel starts compiling,
    ``on_change(False)`` when the last nested compilation ends."""

    def __init__(self, on_change: Callable[[bool], None]):
        from numba.core import event

        class Listener(event.Listener):
            def on_start(inner, ev) -> None:  # noqa: N805 - the outer object keeps the count
                self._step(+1)

            def on_end(inner, ev) -> None:  # noqa: N805
                self._step(-1)

        self.listener = Listener()
        self.on_change = on_change
        self.active = 0
        self._lock = threading.Lock()

    def _step(self, delta: int) -> None:
        with self._lock:
            before, self.active = self.active, self.active + delta
        if before == 0 and self.active > 0:
            self.on_change(True)
        elif before > 0 and self.active == 0:
            self.on_change(False)


@contextlib.contextmanager
def compile_notices(on_change: Callable[[bool], None]) -> Iterator[None]:
    """Within the block, ``on_change(True)`` when numba starts compiling a kernel in this process
    (no usable cache entry) and ``on_change(False)`` when it is done; nothing when kernels load
    from the cache."""
    from numba.core import event

    counter = _CompileCounter(on_change)
    with event.install_listener("numba:compile", counter.listener):
        yield


def main(argv: list[str]) -> int:
    """``python -m slam_engine.kernels [--check]``: warm the cache; with ``--check`` fail (exit 1)
    when anything had to compile (the cache was not warm)."""
    report = warm_up()
    print(f"numba kernels: {len(report['loaded'])} loaded from the cache, {len(report['compiled'])} compiled"
          + (f" ({', '.join(report['compiled'])})" if report["compiled"] else ""))
    missing = [name for name in ENTRY_KERNELS if name not in report["loaded"] + report["compiled"]]
    if missing:
        print(f"numba kernels not run by the warm-up: {', '.join(missing)}", file=sys.stderr)
        return 1
    if "--check" in argv and report["compiled"]:
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
