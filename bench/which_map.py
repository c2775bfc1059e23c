"""Which map among ten: every drive given the same ten saved maps, each must be placed in its own building's,
in at most twice the time of localising it in that map alone, and a drive from a building none of them holds
must be refused by all.

The ten maps, per seed s: the ``a`` halves of the shared datasets' two-session drives (``sessions/``: intel-a,
aces-rough-a, when present), mapped with seed s, and made-up office floors (``building-1`` ... from
:mod:`slam_engine.simulation.buildings`, the robot rig) simulated and mapped with seed s, as many as make ten.
The drives: the ``b`` halves (their odometry starts at an unrelated pose) and each floor driven the other way
round (``building-N-back``, simulated with seed s + 1); the foreign drives: the simulated office (seed s + 1)
and a floor none of the maps holds.

    python -m bench.which_map [--seeds 0-2] [--maps 10]
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import dataclass
from typing import Any

from bench.options import parse_seeds
from slam_engine.config import SlamConfig
from slam_engine.frontend.particle_filter import engine_threads
from slam_engine.model.drive_log import DriveLog
from slam_engine.model.map_bundle import MapBundle
from slam_engine.multisession.localization import localize_log
from slam_engine.multisession.which_map import localize_in_maps
from slam_engine.pipeline import run_slam
from slam_engine.simulation import simulate

MAPS = 10
TIME_RATIO_TARGET = 2.0  # the answer among the maps / localising in the right map alone, at most
SHARED_DRIVES = ("intel", "aces-rough")


@dataclass
class Drive:
    """A drive to place: its ``name``, ``log`` and the map it is in (None: foreign to every map)."""

    name: str
    log: DriveLog
    home: str | None


def maps_and_drives(seed: int, n_maps: int = MAPS, config: SlamConfig | None = None, shared: bool = True
                    ) -> tuple[list[tuple[str, MapBundle]], list[Drive]]:
    """The saved maps ((name, bundle), mapped with ``seed``) and the drives to place (module docstring);
    ``shared`` False: made-up floors only."""
    from bench.sessions import session_drives
    from slam_engine.formats import load_log

    config = config or SlamConfig(seed=seed)

    def mapped(log: DriveLog) -> MapBundle:
        bundle = run_slam(log, config).bundle
        assert bundle is not None  # a mapping run always makes one
        return bundle

    maps: list[tuple[str, MapBundle]] = []
    drives: list[Drive] = []
    for halves in [d for d in session_drives() if d.name in SHARED_DRIVES and shared][:n_maps]:
        maps.append((f"{halves.name}-a", mapped(load_log(halves.a_log))))
        drives.append(Drive(f"{halves.name}-b", load_log(halves.b_log), f"{halves.name}-a"))
    number = 0
    while len(maps) < n_maps:
        number += 1
        name = f"building-{number}"
        maps.append((name, mapped(simulate(name, seed=seed, cameras=False).log)))
        drives.append(Drive(f"{name}-back", simulate(f"{name}-back", seed=seed + 1, cameras=False).log, name))
    drives.append(Drive("office", simulate("office", seed=seed + 1, cameras=False).log, None))
    drives.append(Drive(f"building-{number + 1}", simulate(f"building-{number + 1}", seed=seed + 1,
                                                             cameras=False).log, None))
    return maps, drives


def measure(seed: int, n_maps: int = MAPS, say=print, shared: bool = True) -> list[dict]:
    """One seed's rows: per drive, the map chosen among all, whether it is the right one, the time, and the
    time of localising in the right map alone."""
    config = SlamConfig(seed=seed)
    threads = engine_threads()
    maps, drives = maps_and_drives(seed, n_maps, config, shared)
    bundles = dict(maps)
    rows = []
    for drive in drives:
        found = localize_in_maps(maps, drive.log, config, threads=threads)
        chosen = None if found.chosen is None else found.tries[found.chosen].name
        row: dict[str, Any] = {
            "seed": seed, "drive": drive.name, "home": drive.home, "chosen": chosen, "right": chosen == drive.home,
            "wall_s": found.wall_time_s, "tried": sum(t.localised is not None for t in found.tries),
            "home_rank": next((i + 1 for i, t in enumerate(found.tries) if t.name == drive.home), None)}
        if drive.home is not None:
            started = time.perf_counter()
            localize_log(bundles[drive.home], drive.log, config, threads=threads)
            one_map_s = time.perf_counter() - started
            row.update(one_map_s=one_map_s, time_ratio=found.wall_time_s / one_map_s)
        say(f"  seed {seed}: {drive.name} among {len(maps)} maps: {chosen or 'refused'} "
            f"({'right' if row['right'] else 'WRONG'}; tried {row['tried']}, {found.wall_time_s:.1f} s"
            + (f", {row['one_map_s']:.1f} s in its own map alone)" if "one_map_s" in row else ")"))
        rows.append(row)
    return rows


def table(rows: list[dict], n_maps: int = MAPS) -> str:
    """Per drive over the seeds: right answers, where its map ranked, the time ratio (median / worst) against
    the target (markdown)."""
    names = list(dict.fromkeys(r["drive"] for r in rows))
    lines = [f"| drive | in | right (of seeds) | its map's rank | maps tried | time among {n_maps} / its map alone "
             f"(median / worst; target <= {TIME_RATIO_TARGET:g}) |", "|---|---|---|---|---|---|"]
    for name in names:
        mine = [r for r in rows if r["drive"] == name]
        ratios = [r["time_ratio"] for r in mine if "time_ratio" in r]
        ranks = [str(r["home_rank"]) for r in mine if r["home_rank"] is not None]
        lines.append(f"| {name} | {mine[0]['home'] or 'none (refused)'} | {sum(r['right'] for r in mine)}/{len(mine)} "
                     f"| {', '.join(ranks) or '-'} | {', '.join(str(r['tried']) for r in mine)} | "
                     + (f"{statistics.median(ratios):.2f} / {max(ratios):.2f}" if ratios else
                        f"{statistics.median(r['wall_s'] for r in mine):.1f} s") + " |")
    right = sum(r["right"] for r in rows)
    ratios = [r["time_ratio"] for r in rows if "time_ratio" in r]
    verdict = "PASS" if right == len(rows) and max(ratios) <= TIME_RATIO_TARGET else "FAIL"
    lines.append(f"\nright {right} of {len(rows)}; time ratio median {statistics.median(ratios):.2f}, worst "
                 f"{max(ratios):.2f}; {verdict} (every answer right, every ratio <= {TIME_RATIO_TARGET:g})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.which_map", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="0-2", help="seeds, e.g. 0-4 or 0,3 (default 0-2)")
    parser.add_argument("--maps", type=int, default=MAPS, help=f"saved maps to choose among (default {MAPS})")
    args = parser.parse_args(argv)
    if not 2 <= args.maps <= 50:
        parser.error("--maps must be within 2..50")
    rows = [row for seed in parse_seeds(args.seeds) for row in measure(seed, args.maps)]
    print(table(rows, args.maps))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
