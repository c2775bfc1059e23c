"""Run every (log, seed) in its own child process, one after another, and summarise over seeds.

Peak memory is the child's own maximum resident set size (``os.wait4``), so a run is charged for
what it used and nothing else; runs never overlap, so wall times are not disturbed by each other.
"""

from __future__ import annotations

import contextlib
import json
import os
import platform
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from bench.cases import REPO_ROOT, SOURCE_CHECKOUT, BenchCase
from bench.worker import DEFAULT_LOADER, DEFAULT_RUNNER, finite_or_none

# bench/results in a source checkout; ./bench-results from an installed copy (never into site-packages)
RESULTS_ROOT = REPO_ROOT / "bench" / "results" if SOURCE_CHECKOUT else Path("bench-results").resolve()

# (summary name, path into a run record, worse when higher?)
SLAM_METRICS: tuple[tuple[str, tuple[str, ...], bool], ...] = (
    ("trans_mean_m", ("relations", "all", "trans_mean_m"), True),
    ("rot_mean_deg", ("relations", "all", "rot_mean_deg"), True),
    ("ate_m", ("ate_m",), True),
    ("local_trans_m", ("relations", "local", "trans_mean_m"), True),
    ("local_rot_deg", ("relations", "local", "rot_mean_deg"), True),
    ("loop_trans_m", ("relations", "loop", "trans_mean_m"), True),
    ("loop_rot_deg", ("relations", "loop", "rot_mean_deg"), True),
    ("failed_relations", ("relations", "all", "n_failed"), True),
)
MAP_METRICS: tuple[tuple[str, tuple[str, ...], bool], ...] = (
    ("wall_thickness_m", ("wall_thickness_m",), True),
    ("occupied_with_neighbour", ("occupied_with_neighbour",), False),
    ("half_agreement", ("half_agreement",), False),
    ("half_mean_offset_m", ("half_mean_offset_m",), True),
    # the share of key frames the map contradicts (slam_engine.evaluation.consistency): every log
    ("contradicted_key_frames", ("contradicted_key_frames",), True),
)


@dataclass
class BenchOptions:
    """What to run: seeds, particle count, config overrides (nested dict for SlamConfig), the
    loader and runner functions (``module:function``), output folder and a per-run time limit."""

    seeds: list[int] = field(default_factory=lambda: [0, 1, 2, 3, 4])
    particles: int | None = None  # None: the SlamConfig default
    config: dict = field(default_factory=dict)
    loader: str = DEFAULT_LOADER
    runner: str = DEFAULT_RUNNER
    out_dir: Path | None = None
    timeout_s: float = 3600.0
    extra_pythonpath: list[str] = field(default_factory=list)
    busy: int = 0  # CPU-bound processes kept running beside every run (a busy machine)


def _get(record: dict | None, path: tuple[str, ...]):
    for key in path:
        if not isinstance(record, dict):
            return None
        record = record.get(key)
    return record


BUSY_LOOP = "while True: pass"


@contextlib.contextmanager
def busy_processes(n: int) -> Iterator[list[subprocess.Popen]]:
    """``n`` CPU-bound Python processes (``while True: pass``) for the duration of the block."""
    children = [subprocess.Popen([sys.executable, "-c", BUSY_LOOP]) for _ in range(n)]
    try:
        yield children
    finally:
        for child in children:
            child.kill()
            child.wait()


def run_one(case: BenchCase, seed: int, options: BenchOptions, out_dir: Path) -> dict:
    """Run one (case, seed) in a child process; the record the worker wrote, plus peak memory."""
    stem = f"{case.name}_seed{seed}"
    job_path, result_path = out_dir / f"{stem}.job.json", out_dir / f"{stem}.json"
    job = {"case": case.as_dict(), "seed": seed, "particles": options.particles, "config": options.config,
           "loader": options.loader, "runner": options.runner, "out_dir": str(out_dir)}
    job_path.write_text(json.dumps(job, indent=1))
    result_path.unlink(missing_ok=True)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO_ROOT), *options.extra_pythonpath,
                                         *filter(None, [env.get("PYTHONPATH")])])
    log_path = out_dir / f"{stem}.stderr.txt"
    started = time.perf_counter()
    with log_path.open("w") as stderr, busy_processes(options.busy):
        child = subprocess.Popen([sys.executable, "-m", "bench.worker", str(job_path), str(result_path)],
                                 cwd=REPO_ROOT, env=env, stdout=stderr, stderr=subprocess.STDOUT)
        timer = threading.Timer(options.timeout_s, child.kill)
        timer.start()
        try:
            _, status, usage = os.wait4(child.pid, 0)
        finally:
            timer.cancel()
        child.returncode = os.waitstatus_to_exitcode(status)
    process_s = time.perf_counter() - started
    if child.returncode == 0 and result_path.exists():
        record = json.loads(result_path.read_text())
    else:
        tail = log_path.read_text()[-2000:].strip()
        reason = f"killed after {options.timeout_s:.0f} s" if child.returncode == -9 else \
            f"exit code {child.returncode}"
        record = {"case": case.name, "log_path": case.log_path, "scored": case.scored, "seed": seed,
                  "particles": options.particles, "status": "error", "error": f"{reason}: {tail}"}
    # the worker's own high-water mark; wait4's ru_maxrss also counts this process's size when it
    # started the worker (Linux), which it only falls back on (a worker that failed)
    record["peak_memory_mb"] = record.pop("peak_process_mb", None) or usage.ru_maxrss / 1024.0  # KiB
    record["process_s"] = process_s
    if record.get("scoring_s") is not None:  # the whole process as `lidarmap run` costs it: no scoring
        record["run_process_s"] = process_s - record["scoring_s"]
    result_path.write_text(json.dumps(finite_or_none(record), indent=1))
    return record


def _spread(values: list, worse_when_higher: bool) -> dict:
    """Median and worst over seeds (None when no seed has the number)."""
    present = [v for v in values if v is not None]
    if not present:
        return {"median": None, "worst": None}
    return {"median": statistics.median(present), "worst": max(present) if worse_when_higher else min(present)}


def summarise(case: BenchCase, records: list[dict]) -> dict:
    """One case over its seeds: timing medians, peak memory maximum, metric median and worst seed,
    dead reckoning (seed-independent: taken from the first successful run)."""
    ok = [r for r in records if r.get("status") == "ok"]
    first = ok[0] if ok else {}
    summary = {
        "case": case.name, "log_path": case.log_path, "scored": case.scored,
        "seeds": [r["seed"] for r in records], "seeds_ok": len(ok),
        "errors": {str(r["seed"]): r.get("error") for r in records if r.get("status") != "ok"},
        "particles": (first or (records[0] if records else {})).get("particles"),
        "scans": first.get("scans"), "duration_s": first.get("duration_s"),
        "wall_s": _spread([r.get("wall_s") for r in ok], True)["median"],
        "products_s": _spread([r.get("products_s") for r in ok], True)["median"],
        "products_share": _spread([r.get("products_share") for r in ok], True)["median"],
        "process_s": _spread([r.get("process_s") for r in ok], True)["median"],
        "run_process_s": _spread([r.get("run_process_s") for r in ok], True)["median"],
        "scans_per_s": _spread([r.get("scans_per_s") for r in ok], False)["median"],
        "realtime_factor": _spread([r.get("realtime_factor") for r in ok], False)["median"],
        "peak_memory_mb": max((r["peak_memory_mb"] for r in records if r.get("peak_memory_mb")), default=None),
        "peak_run_mb": max((r["peak_run_mb"] for r in ok if r.get("peak_run_mb")), default=None),
        "slam": {name: _spread([_get(r["slam"], path) for r in ok], worse) for name, path, worse in SLAM_METRICS},
        "dead_reckoning": {name: _get(first.get("dead_reckoning"), path) for name, path, _ in SLAM_METRICS},
        "map": {name: _spread([_get(r.get("map"), path) for r in ok], worse) for name, path, worse in MAP_METRICS},
        "dead_reckoning_map": {name: _get(first.get("dead_reckoning_map"), path)
                               for name, path, _ in MAP_METRICS if name.startswith("half")},
        "map_pngs": [r["map_png"] for r in ok if r.get("map_png")],
        # runs whose map was flagged, those where the back end tried alternatives, those that kept one
        "flagged_runs": sum(1 for r in ok if r.get("flagged_retry")),
        "flagged_retries": sum(1 for r in ok if (r.get("flagged_retry") or {}).get("alternatives")),
        "alternatives_kept": sum(1 for r in ok if (r.get("flagged_retry") or {}).get("kept", "the first map")
                                 != "the first map"),
    }
    return finite_or_none(summary)


def code_version() -> dict:
    """The checkout's commit and whether it had uncommitted changes (None outside git)."""
    def git(*args: str) -> str | None:
        try:
            return subprocess.run(["git", *args], cwd=REPO_ROOT, capture_output=True, text=True,
                                  check=True, timeout=10).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return None

    status = git("status", "--porcelain")
    return {"commit": git("rev-parse", "HEAD"), "dirty": None if status is None else bool(status)}


def write_results(results: dict, out_dir: Path, name: str, latest_name: str) -> None:
    """``results`` as JSON into ``out_dir / name`` and, when ``out_dir`` lies under :data:`RESULTS_ROOT`,
    a copy as ``RESULTS_ROOT / latest_name`` (the newest run of that table)."""
    text = json.dumps(results, indent=1)
    (out_dir / name).write_text(text)
    if out_dir.resolve().is_relative_to(RESULTS_ROOT.resolve()):
        (RESULTS_ROOT / latest_name).write_text(text)


def default_out_dir() -> Path:
    return RESULTS_ROOT / time.strftime("%Y%m%d-%H%M%S")


def run_benchmark(cases: list[BenchCase], options: BenchOptions,
                  on_run: Callable[[dict], None] | None = None) -> dict:
    """Run every case for every seed, sequentially; write ``results.json`` in the output folder
    (and a copy as ``bench/results/latest.json`` when writing under ``bench/results``) and return it."""
    out_dir = Path(options.out_dir) if options.out_dir is not None else default_out_dir()
    out_dir.mkdir(parents=True, exist_ok=True)
    load_at_start = list(os.getloadavg())  # other work on the machine disturbs the timings
    runs, summaries = [], []
    for case in cases:
        records = []
        for seed in options.seeds:
            record = run_one(case, seed, options, out_dir)
            records.append(record)
            if on_run is not None:
                on_run(record)
        runs.extend(records)
        summaries.append(summarise(case, records))
    results = {
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "machine": {"platform": platform.platform(), "python": platform.python_version(),
                    "cpu_count": os.cpu_count(), "processor": platform.processor(),
                    "load_average_at_start": load_at_start, "load_average_at_end": list(os.getloadavg())},
        "code": code_version(),
        "options": {"seeds": options.seeds, "particles": options.particles, "config": options.config,
                    "loader": options.loader, "runner": options.runner, "timeout_s": options.timeout_s,
                    "busy": options.busy},
        "cases": [case.as_dict() for case in cases],
        "summaries": summaries,
        "runs": [finite_or_none(r) for r in runs],
        "out_dir": str(out_dir),
    }
    write_results(results, out_dir, "results.json", "latest.json")
    return results
