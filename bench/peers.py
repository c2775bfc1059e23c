"""Side by side with Karto (the fastest peer, the core slam_toolbox grew from): whole processes,
interleaved on one machine (lidarmap, Karto, lidarmap, Karto, ...), the median of each and their ratio.

Karto is built from ``../shared/peers`` (its README: ``build_karto.sh`` writes
``$TMPDIR/peers/bin/karto_carmen``; ``LIDARMAP_KARTO`` names another binary). Without it the table says
how to build it. lidarmap runs as a user runs it: ``lidarmap run LOG --out DIR --seed S`` (products and
scoring included); Karto writes its poses only.

    python -m bench.peers [--rounds 3] [LOG ...]   # default: aces-rough, infinite-corridor-rough, intel
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from bench.cases import datasets_root

DEFAULT_LOGS = ("aces-rough", "infinite-corridor-rough", "intel")


def karto_binary() -> Path | None:
    """The Karto driver, if built: ``LIDARMAP_KARTO``, else where ``build_karto.sh`` puts it."""
    named = os.environ.get("LIDARMAP_KARTO")
    path = Path(named) if named else Path(tempfile.gettempdir()) / "peers" / "bin" / "karto_carmen"
    return path if path.is_file() and os.access(path, os.X_OK) else None


@dataclass
class SideBySide:
    """One log's whole-process times [s], per round."""

    log: str
    lidarmap_s: list[float]
    karto_s: list[float]

    @property
    def ratio(self) -> float:
        return statistics.median(self.lidarmap_s) / statistics.median(self.karto_s)

    def row(self) -> str:
        return (f"| {self.log} | {statistics.median(self.lidarmap_s):.2f} | {statistics.median(self.karto_s):.2f} | "
                f"{self.ratio:.2f} |")


def _timed(command: list[str]) -> float:
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed ({done.returncode}): {done.stderr.strip()[-300:]}")
    return time.perf_counter() - started


def side_by_side(log: Path, karto: Path, rounds: int, seed: int = 0) -> SideBySide:
    """``rounds`` interleaved pairs of whole processes on ``log``."""
    lidarmap = [sys.executable, "-m", "lidarmap.cli", "run", str(log), "--seed", str(seed), "--force", "--out"]
    result = SideBySide(log.stem.split(".")[0], [], [])
    with tempfile.TemporaryDirectory(prefix="bench-peers-") as scratch:
        for _ in range(rounds):
            result.lidarmap_s.append(_timed([*lidarmap, str(Path(scratch) / "lidarmap")]))
            result.karto_s.append(_timed([str(karto), str(log), str(Path(scratch) / "karto.txt")]))
            shutil.rmtree(Path(scratch) / "lidarmap", ignore_errors=True)
    return result


def table(rows: list[SideBySide], rounds: int) -> str:
    head = "| log | lidarmap [s] | Karto [s] | lidarmap / Karto |\n|---|---|---|---|"
    note = f"(whole processes, median of {rounds} interleaved rounds)"
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
