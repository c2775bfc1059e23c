"""A robot carried off (kidnapped), fed to a live localisation one scan at a time, each search waited for (as if
it took no time).

- Made-up office floors: each floor (``building-N``) mapped with seed 0, then driven again (seed 1) and carried
  30 s in to where it would have been 20 s later. Per floor: the jump, how far it drove after it until reported
  lost, until found again (None: not within the drive), and how many scans after it were reported found more
  than 0.3 m from the truth (the target: none); and the next floor's drive (``building-N+1``, seed 2; the
  eighth's: the first's) in this floor's map: how many of its scans were reported found (the target: none; the
  floors are made by one recipe and look alike in places).
- The simulated office (mapped with seed 0, driven again with seed 1), nearly symmetric under a half turn:
  carried off 20, 30 and 40 s in to where it would have been 10, 20 and 30 s later, often to a place that
  looks like where it was. The same columns.

    python -m bench.kidnap
"""

from __future__ import annotations

import argparse
import statistics

import numpy as np

from slam_engine.config import SlamConfig
from slam_engine.evaluation.metrics import align_rigid_2d
from slam_engine.frontend.odometry import dead_reckoning
from slam_engine.frontend.particle_filter import make_projector
from slam_engine.multisession.live_localization import FOUND, LOST, LiveLocalizer
from slam_engine.pipeline import run_slam
from slam_engine.simulation import SimulatedDrive, simulate

KIDNAP = (30.0, 20.0)  # carried off this far into the drive [s], to where it would have been this much later [s]
WRONG_M = 0.3  # a found pose farther than this from the truth [m] is confidently wrong
REFIND_TARGET_M = 10.0  # found again within this much driving after the kidnap [m]
FLOORS = 8  # building-1 .. building-8
OFFICE_KIDNAPS = tuple((at, skip) for at in (20.0, 30.0, 40.0) for skip in (10.0, 20.0, 30.0))  # [s], [s]


def stream(bundle, drive: SimulatedDrive, config: SlamConfig) -> tuple[LiveLocalizer, list]:
    """The drive's scans fed one by one, each search waited for (as if it took no time): the localiser and
    (scan, report) per scan, a scan whose search placed the drive with that report."""
    log = drive.log
    assert log.scans is not None and log.lidar is not None
    odometry = dead_reckoning(log).poses
    projector = make_projector(log.lidar, config, no_return_bounded=False)
    live = LiveLocalizer(bundle, config)
    reports = []
    for i in range(len(log.scans)):
        reports.append((i, live.add(log.scans.t_s[i], odometry[i], projector.project(log.scans.ranges_m[i]).hits_v)))
        again = live.wait()
        if again is not None:
            reports[-1] = (i, again)
    live.close()
    return live, reports


def kidnapped(bundle, rotation: np.ndarray, translation: np.ndarray, drive: SimulatedDrive,
              config: SlamConfig) -> dict:
    """A kidnapped ``drive`` streamed into the map of ``bundle`` (whose frame ``rotation`` and ``translation``
    carry onto the world): the jump [m], the travel after it until reported lost and until found again [m]
    (None: not within the drive), the scans after it reported found more than WRONG_M off, the travel left."""
    assert drive.log.scans is not None
    truth = drive.pose_at(drive.log.scans.t_s)
    steps = np.hypot(*np.diff(truth[:, :2], axis=0).T)
    kidnap = int(np.argmax(steps))
    driven = np.concatenate([[0.0], np.cumsum(np.where(steps > 1.0, 0.0, steps))])  # driven, not carried [m]
    since = driven - driven[kidnap + 1]
    _, reports = stream(bundle, drive, config)
    after = [(i, r) for i, r in reports if i > kidnap]
    error = {i: float(np.hypot(*(r.pose[:2] @ rotation.T + translation - truth[i, :2]))) for i, r in after
             if r.pose is not None}
    lost = next((i for i, r in after if r.state == LOST), None)
    found = next((i for i, r in after if r.state == FOUND and lost is not None and i > lost), None)
    return {"jump_m": float(steps[kidnap]), "lost_after_m": None if lost is None else since[lost],
            "found_after_m": None if found is None else since[found],
            "wrong": sum(r.state == FOUND and error[i] > WRONG_M for i, r in after), "driven_after_m": since[-1]}


def _mapped(scenario: str, config: SlamConfig) -> tuple:
    """``scenario`` mapped with seed 0: its bundle and the rotation and translation onto the world."""
    mapped = simulate(scenario, seed=0, cameras=False)
    result = run_slam(mapped.log, config)
    rotation, translation = align_rigid_2d(result.trajectory.poses[:, :2],
                                           mapped.pose_at(result.trajectory.t_s)[:, :2])
    return result.bundle, rotation, translation


def measure(number: int, config: SlamConfig | None = None) -> dict:
    """One floor's row (module docstring)."""
    config = config or SlamConfig(seed=0)
    name = f"building-{number}"
    bundle, rotation, translation = _mapped(name, config)
    row = {"building": name, **kidnapped(bundle, rotation, translation,
                                         simulate(name, seed=1, cameras=False, kidnap=KIDNAP), config)}
    foreign = simulate(f"building-{number % FLOORS + 1}", seed=2, cameras=False)
    return {**row, "foreign_found": sum(r.state == FOUND for _, r in stream(bundle, foreign, config)[1]),
            "foreign_scans": len(foreign.log.scans or [])}


def office_rows(config: SlamConfig | None = None, kidnaps: tuple = OFFICE_KIDNAPS) -> list[dict]:
    """The office's rows (module docstring), one per (at [s], skip [s]) in ``kidnaps``."""
    config = config or SlamConfig(seed=0)
    bundle, rotation, translation = _mapped("office", config)
    return [{"kidnap": kidnap, **kidnapped(bundle, rotation, translation,
                                           simulate("office", seed=1, cameras=False, kidnap=kidnap), config)}
            for kidnap in kidnaps]


def table(rows: list[dict]) -> str:
    """The floors' rows and a summary against the targets (markdown)."""
    def m(value: float | None) -> str:
        return "-" if value is None else f"{value:.1f}"

    lines = ["| floor | jump [m] | lost after [m] | found again after [m] | found > 0.3 m off (scans) "
             "| driven after [m] | the next floor's drive here: found (scans) |", "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['building']} | {r['jump_m']:.1f} | {m(r['lost_after_m'])} | {m(r['found_after_m'])} | "
              f"{r['wrong']} | {r['driven_after_m']:.1f} | {r['foreign_found']} of {r['foreign_scans']} |"
              for r in rows]
    found = [r["found_after_m"] for r in rows if r["found_after_m"] is not None]
    lines.append(f"\nfound again on {len(found)} of {len(rows)} floors"
                 + (f" (median {statistics.median(found):.1f} m; target <= {REFIND_TARGET_M:g} m)" if found else "")
                 + f"; confidently wrong scans {sum(r['wrong'] for r in rows)} (target 0); the next floor's drive "
                 f"found in {sum(r['foreign_found'] > 0 for r in rows)} of {len(rows)} maps (target 0)")
    return "\n".join(lines)


def office_table(rows: list[dict]) -> str:
    """The office's rows and a summary against the targets (markdown)."""
    def m(value: float | None) -> str:
        return "-" if value is None else f"{value:.1f}"

    lines = ["| carried off at [s] | to where it would be [s] later | jump [m] | lost after [m] "
             "| found again after [m] | found > 0.3 m off (scans) | driven after [m] |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['kidnap'][0]:g} | {r['kidnap'][1]:g} | {r['jump_m']:.1f} | {m(r['lost_after_m'])} | "
              f"{m(r['found_after_m'])} | {r['wrong']} | {r['driven_after_m']:.1f} |" for r in rows]
    found = [r["found_after_m"] for r in rows if r["found_after_m"] is not None]
    lines.append(f"\nfound again after {len(found)} of {len(rows)} kidnaps"
                 + (f" (median {statistics.median(found):.1f} m; target <= {REFIND_TARGET_M:g} m)" if found else "")
                 + f"; confidently wrong scans {sum(r['wrong'] for r in rows)} (target 0)")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.kidnap", description=__doc__.split("\n\n")[0])
    parser.parse_args(argv)
    print(table([measure(n) for n in range(1, FLOORS + 1)]))
    print("\nThe office, nearly symmetric under a half turn:")
    print(office_table(office_rows()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
