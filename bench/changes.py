"""The change map against known changes: the simulated office mapped, then driven again days later with a
desk moved, a pillar taken away, a door closed and a partition put up (``office-changed``, whose
``changes.json`` is the truth), localised in that map without a start pose; and the unchanged office
driven again, where nothing changed. Per seed s: the office mapped with seed s, the later drives
simulated with seed s + 1.

Cell-level precision and recall with a one-cell tolerance (:mod:`slam_engine.evaluation.changes`);
the share of the observed area reported changed; the change map's time against the localisation's.

    python -m bench.changes [--seeds 0-4]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from bench.options import parse_seeds
from slam_engine.config import SlamConfig
from slam_engine.evaluation.changes import change_accuracy
from slam_engine.evaluation.metrics import align_rigid_2d, match_times
from slam_engine.multisession.changes import localization_changes
from slam_engine.multisession.localization import localize_log
from slam_engine.pipeline import run_slam
from slam_engine.products.multisession import saved_map_grid
from slam_engine.simulation import simulate

TARGETS = {"precision": 0.9, "recall": 0.8, "unchanged_share": 0.01, "time_ratio": 0.1}


def measure(seed: int, config: SlamConfig | None = None) -> dict:
    """One seed's figures (see the module docstring)."""
    config = config or SlamConfig(seed=seed)
    bundle = run_slam(simulate("office", seed=seed, cameras=False).log, config).bundle
    assert bundle is not None
    grid = saved_map_grid(bundle, config)
    out: dict = {"seed": seed}
    for name in ("office-changed", "office"):
        later = simulate(name, seed=seed + 1, cameras=False)
        started = time.perf_counter()
        drive, result = localize_log(bundle, later.log, config)
        localise_s = time.perf_counter() - started
        changes = localization_changes(grid, drive, result, config.changes)
        if changes is None or result.trajectory is None:
            out[name] = {"localised": False}
            continue
        summary = changes.summary()
        record = {"localised": True, "share": summary["changed_share"], "changes_s": changes.wall_time_s,
                  "localise_s": localise_s, "time_ratio": changes.wall_time_s / localise_s}
        if name == "office-changed":
            index = match_times(later.ground_truth.t_s, result.trajectory.t_s)
            kept = index >= 0
            rotation, translation = align_rigid_2d(later.ground_truth.poses[index[kept], :2],
                                                   result.trajectory.poses[kept, :2])
            T_map_from_world = np.array([*translation, np.arctan2(rotation[1, 0], rotation[0, 0])])
            accuracy = change_accuracy(changes, later.world.removed, later.world.added, T_map_from_world)
            record.update(precision=accuracy["precision"], recall=accuracy["recall"],
                          added_recall=accuracy["added"]["recall"], removed_recall=accuracy["removed"]["recall"])
        out[name] = record
    return out


def table(rows: list[dict]) -> str:
    """The seeds' figures and their medians against the targets (markdown)."""
    def figure(row: dict, name: str, key: str) -> float | None:
        value = row.get(name, {}).get(key)
        return None if value is None else float(value)

    columns = [("office-changed", "precision", "precision"), ("office-changed", "recall", "recall"),
               ("office-changed", "added_recall", "recall added"), ("office-changed", "removed_recall",
                                                                    "recall removed"),
               ("office-changed", "share", "changed share"), ("office", "share", "unchanged: changed share"),
               ("office-changed", "time_ratio", "change map / localise")]
    lines = ["| seed | " + " | ".join(label for _, _, label in columns) + " |",
             "|---" * (len(columns) + 1) + "|"]
    for row in rows:
        cells = [figure(row, name, key) for name, key, _ in columns]
        lines.append(f"| {row['seed']} | " + " | ".join("–" if c is None else f"{c:.3f}" for c in cells) + " |")
    medians = []
    for name, key, _ in columns:
        values = [v for v in (figure(r, name, key) for r in rows) if v is not None]
        medians.append("–" if not values else f"{statistics.median(values):.3f}")
    lines.append("| median | " + " | ".join(medians) + " |")
    lines.append(f"\ntargets: precision >= {TARGETS['precision']}, recall >= {TARGETS['recall']} (objects >= 0.3 m); "
                 f"unchanged share <= {TARGETS['unchanged_share']}; change map <= {TARGETS['time_ratio']} of "
                 "localising")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="0-4")
    args = parser.parse_args(argv)
    print(table([measure(seed) for seed in parse_seeds(args.seeds)]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
