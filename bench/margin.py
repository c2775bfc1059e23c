"""``python -m bench margin``: how far the sparse logs are from losing their map, at fewer particles
than the default and over more seeds than the main table.

The logs whose scans are about a metre apart (``aces-rough``, ``infinite-corridor-rough`` of the shared
benchmark) hold at the default 30 particles but lose their map at 15-20 on some seeds. Each (log, seed)
is mapped in its own process (as ``python -m bench`` does) with ``--particles`` (15) over ``--seeds``
(0-9); a map counts as *lost* when its relation error (all relations, mean translation) is above
:data:`LOST_M` or the run failed. Prints one table (lost of seeds, median, worst, every seed's error)
and writes ``margin.json`` into the results folder (with a copy as ``bench/results/latest-margin.json``
when under ``bench/results``).
"""

from __future__ import annotations

import statistics
from pathlib import Path

import typer

from bench.options import SEEDS_HELP, parse_seeds, read_overrides, report_console

MARGIN_LOGS = ("aces-rough", "infinite-corridor-rough")  # benchmark logs with scans about 1 m apart
MARGIN_PARTICLES = 15
MARGIN_SEEDS = "0-9"
LOST_M = 0.10  # a relation error above this [m]: the map is lost
RESULTS_FILE = "margin.json"
LATEST_FILE = "latest-margin.json"


def relation_error_m(record: dict) -> float | None:
    """A run's relation error (all relations, mean translation) [m]; None when the run failed."""
    if record.get("status") != "ok":
        return None
    return ((record.get("slam") or {}).get("relations") or {}).get("all", {}).get("trans_mean_m")


def margin_row(name: str, records: list[dict], lost_m: float = LOST_M) -> dict:
    """One log's line: the seeds, each one's error (None: failed), how many are lost (failed or above
    ``lost_m``), and the median and worst error of the runs that finished."""
    errors = [relation_error_m(r) for r in records]
    finished = [e for e in errors if e is not None]
    lost = [r["seed"] for r, e in zip(records, errors, strict=True) if e is None or e > lost_m]
    return {"log": name, "seeds": [r["seed"] for r in records], "errors_m": errors, "lost_seeds": lost,
            "lost": len(lost), "runs": len(records),
            "median_m": statistics.median(finished) if finished else None,
            "worst_m": max(finished) if finished else None}


def margin_cases(logs: tuple[str, ...] = MARGIN_LOGS) -> list:
    """The benchmark logs of the shared datasets named in ``logs`` (those present)."""
    from bench.cases import default_cases

    return [case for case in default_cases(map_only=False) if case.name in logs]


def run_margin(cases: list, options, say=print) -> dict:
    """Map each of ``cases`` for every seed of ``options`` (a :class:`bench.harness.BenchOptions`: its
    particles, config, runner and ``out_dir``), one process each; the table's rows as JSON, also
    written to ``options.out_dir / RESULTS_FILE``."""
    from bench.harness import code_version, run_one, write_results

    out = Path(options.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in cases:
        records = []
        for seed in options.seeds:
            record = run_one(case, seed, options, out)
            records.append(record)
            error = relation_error_m(record)
            say(f"  margin: {case.name} seed {seed}, {options.particles} particles: "
                + ("failed" if error is None else f"{error:.3f} m"))
        rows.append(margin_row(case.name, records))
    results = {"code": code_version(), "particles": options.particles, "seeds": options.seeds,
               "config": options.config, "lost_m": LOST_M, "rows": rows, "out_dir": str(out)}
    write_results(results, out, RESULTS_FILE, LATEST_FILE)
    return results


def run_margin_table(out: Path, seeds: list[int], particles: int, overrides: dict, console) -> None:
    """The margin table over the shared datasets' sparse logs into ``out / "margin"``, printed."""
    from bench.harness import BenchOptions

    cases = margin_cases()
    if not cases:
        console.print(f"[yellow]margin table skipped:[/yellow] none of {', '.join(MARGIN_LOGS)} among the "
                      "benchmark logs", highlight=False)
        return
    options = BenchOptions(seeds=seeds, particles=particles, config=overrides, out_dir=out / "margin")
    print_margin(run_margin(cases, options, say=lambda line: console.print(line, highlight=False)), console)


def print_margin(results: dict, console) -> None:
    """The margin table: one line per log."""
    from rich.table import Table

    from bench.report import fmt

    table = Table(title=f"Margin: {results['particles']} particles, seeds {results['seeds'][0]}-"
                        f"{results['seeds'][-1]} (lost: relation error above {results['lost_m']:.2f} m or failed)")
    for column in ("log", "lost", "median / worst (m)", "every seed (m)"):
        table.add_column(column)
    for row in results["rows"]:
        every = ", ".join("failed" if e is None else f"{e:.3f}" for e in row["errors_m"])
        table.add_row(row["log"], f"{row['lost']} of {row['runs']}",
                      f"{fmt(row['median_m'], 3)} / {fmt(row['worst_m'], 3)}", every)
    console.print(table)


def margin(
    seeds: str = typer.Option(MARGIN_SEEDS, help=SEEDS_HELP),
    particles: int = typer.Option(MARGIN_PARTICLES, min=1, max=1000, help="Particles per run."),
    config: Path | None = typer.Option(None, exists=True, dir_okay=False,
                                       help="YAML or JSON file with SlamConfig overrides."),
    out: Path | None = typer.Option(None, help="Output folder (default bench/results/<date-time>)."),
) -> None:
    """The sparse logs (scans a metre apart) at fewer particles over ten seeds: how many lose their map."""
    from bench.harness import default_out_dir

    run_margin_table(out if out is not None else default_out_dir(), parse_seeds(seeds), particles,
                     read_overrides(config) or {}, report_console())
