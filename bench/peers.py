"""Side by side with Karto (the fastest peer, the core slam_toolbox grew from): whole processes,
interleaved on one machine (lidarmap, Karto, lidarmap, Karto, ...), the median of each and their ratio,
beside each one's peak memory and relation error on the log (what the time buys: a ratio alone does
not say that Karto's corridor map is lost).

Karto is built from ``../shared/peers`` (its README: ``build_karto.sh`` writes
``$TMPDIR/peers/bin/karto_carmen``; ``LIDARMAP_KARTO`` names another binary). Without it the table says
how to build it. lidarmap runs as a user runs it: ``lidarmap run LOG --out DIR --seed S`` (products and
scoring included); Karto writes its poses only. Karto's poses are scored against ``NAME.relations``
beside the log like lidarmap's (relations at scans it skipped, below its minimum travel, are not
matched: the table says how many were), lidarmap's error is its run's own ``run.json``.

    python -m bench.peers [--rounds 3] [LOG ...]   # default: aces-rough, infinite-corridor-rough, intel
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bench.cases import datasets_root

DEFAULT_LOGS = ("aces-rough", "infinite-corridor-rough", "intel")


def karto_binary() -> Path | None:
    """The Karto driver, if built: ``LIDARMAP_KARTO``, else where ``build_karto.sh`` puts it."""
    named = os.environ.get("LIDARMAP_KARTO")
    path = Path(named) if named else Path(tempfile.gettempdir()) / "peers" / "bin" / "karto_carmen"
    return path if path.is_file() and os.access(path, os.X_OK) else None


@dataclass
class Scored:
    """A trajectory's mean relation error [m] over the relations it could be matched at."""

    trans_mean_m: float
    matched: int
    relations: int

    def cell(self) -> str:
        if self.matched == 0:
            return "–"
        text = f"{self.trans_mean_m:.3f}"
        return text if self.matched == self.relations else f"{text} ({self.matched}/{self.relations})"


@dataclass
class SideBySide:
    """One log's whole-process times [s] and peak memory [MB] per round, and each one's relation error
    (None without relations beside the log)."""

    log: str
    lidarmap_s: list[float]
    karto_s: list[float]
    lidarmap_peak_mb: list[float] = field(default_factory=list)
    karto_peak_mb: list[float] = field(default_factory=list)
    lidarmap_error: Scored | None = None
    karto_error: Scored | None = None

    @property
    def ratio(self) -> float:
        return statistics.median(self.lidarmap_s) / statistics.median(self.karto_s)

    def row(self) -> str:
        peaks = "–" if not self.lidarmap_peak_mb or not self.karto_peak_mb else \
            f"{statistics.median(self.lidarmap_peak_mb):.0f} / {statistics.median(self.karto_peak_mb):.0f}"
        errors = "–" if self.lidarmap_error is None or self.karto_error is None else \
            f"{self.lidarmap_error.cell()} / {self.karto_error.cell()}"
        return (f"| {self.log} | {statistics.median(self.lidarmap_s):.2f} | {statistics.median(self.karto_s):.2f} | "
                f"{self.ratio:.2f} | {peaks} | {errors} |")


# Runs the command as its own child and writes that child's peak resident memory [KB] and wall time [s]
# (from its fork to its end: the helper's own start is not counted) into argv[1]. A child's peak counts
# its parent's at the fork (Linux carries the high-water mark over into exec): timed straight from this
# process (hundreds of MB inside `make bench`), every command read at least that. Forked from this small
# helper instead, a command cannot read below the helper's few MB.
_PEAK_HELPER = """import os, sys, time
started = time.perf_counter()
pid = os.fork()
if pid == 0:
    os.execvp(sys.argv[2], sys.argv[2:])
_, status, usage = os.wait4(pid, 0)
wall_s = time.perf_counter() - started
with open(sys.argv[1], "w") as out:
    out.write(f"{usage.ru_maxrss} {wall_s!r}")
sys.exit(os.waitstatus_to_exitcode(status))
"""


def _timed(command: list[str]) -> tuple[float, float]:
    """Wall time [s] and peak resident memory [MB] of one whole process (:data:`_PEAK_HELPER`)."""
    with tempfile.TemporaryDirectory(prefix="bench-peak-") as scratch:
        figures = Path(scratch) / "figures"
        done = subprocess.run([sys.executable, "-c", _PEAK_HELPER, str(figures), *command],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, check=False)
        if done.returncode != 0:
            tail = done.stderr.decode(errors="replace").strip()[-300:]
            raise RuntimeError(f"{' '.join(command)} failed ({done.returncode}): {tail}")
        peak_kb, wall_s = figures.read_text().split()
        return float(wall_s), int(peak_kb) / 1024.0  # Linux: kilobytes


def lidarmap_error(out_dir: Path) -> Scored | None:
    """lidarmap's relation error from its run's ``run.json`` (None when the run had no relations)."""
    figures = ((json.loads((out_dir / "run.json").read_text()).get("accuracy") or {}).get("relations") or {}).get("all")
    if not figures:
        return None
    n = int(figures["n_relations"])
    return Scored(float(figures["trans_mean_m"]), n - int(figures["n_failed"]), n)


def karto_error(poses_path: Path, relations_path: Path) -> Scored | None:
    """Karto's ``t x y theta`` poses scored against the log's relations (None without them)."""
    from slam_engine.evaluation.metrics import read_relations, relation_errors
    from slam_engine.model.result import Trajectory

    if not relations_path.is_file():
        return None
    relations = read_relations(relations_path)
    rows = np.loadtxt(poses_path, ndmin=2)
    if len(rows) == 0:
        return Scored(float("nan"), 0, len(relations))
    stats = relation_errors(Trajectory(rows[:, 0], rows[:, 1:4]), relations).all
    return Scored(stats.trans_mean_m, stats.n_scored, stats.n_relations)


def side_by_side(log: Path, karto: Path, rounds: int, seed: int = 0) -> SideBySide:
    """``rounds`` interleaved pairs of whole processes on ``log``; the errors of the last round."""
    lidarmap = [sys.executable, "-m", "lidarmap.cli", "run", str(log), "--seed", str(seed), "--force", "--out"]
    name = log.name.split(".")[0]
    result = SideBySide(name, [], [])
    with tempfile.TemporaryDirectory(prefix="bench-peers-") as scratch:
        out, poses = Path(scratch) / "lidarmap", Path(scratch) / "karto.txt"
        for _ in range(rounds):
            shutil.rmtree(out, ignore_errors=True)
            wall_s, peak_mb = _timed([*lidarmap, str(out)])
            result.lidarmap_s.append(wall_s)
            result.lidarmap_peak_mb.append(peak_mb)
            wall_s, peak_mb = _timed([str(karto), str(log), str(poses)])
            result.karto_s.append(wall_s)
            result.karto_peak_mb.append(peak_mb)
        result.lidarmap_error = lidarmap_error(out)
        result.karto_error = karto_error(poses, log.with_name(f"{name}.relations"))
    return result


def table(rows: list[SideBySide], rounds: int) -> str:
    head = ("| log | lidarmap [s] | Karto [s] | lidarmap / Karto | peak lidarmap / Karto [MB] | "
            "relation error lidarmap / Karto [m] |\n|---|---|---|---|---|---|")
    note = (f"(whole processes, median of {rounds} interleaved rounds; relation errors of the last round, "
            "(matched/all) where Karto skipped scans that relations start or end at)")
    return "\n".join([head] + [r.row() for r in rows] + [note])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("logs", nargs="*", default=list(DEFAULT_LOGS),
                        help="benchmark log names, or paths to CARMEN logs")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args(argv)
    karto = karto_binary()
    if karto is None:
        print("Karto is not built: ../shared/peers/build_karto.sh (see ../shared/peers/README.md), or set "
              "LIDARMAP_KARTO")
        return 2
    logs = [Path(n) if n.endswith((".clf", ".log", ".gz")) else datasets_root() / "benchmark" / f"{n}.clf"
            for n in args.logs]
    print(table([side_by_side(log, karto, max(1, args.rounds)) for log in logs], args.rounds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
