"""Rich tables of a benchmark's ``results.json``: one table per log, SLAM vs dead reckoning."""

from __future__ import annotations

from rich.console import Console
from rich.table import Table


def fmt(value, digits: int = 3) -> str:
    """A number with ``digits`` decimals, or an en dash when missing."""
    if value is None:
        return "–"
    if isinstance(value, int):
        return str(value)
    return f"{value:.{digits}f}"


def _median_worst(spread: dict | None, digits: int) -> str:
    if not spread or spread.get("median") is None:
        return "–"
    return f"{fmt(spread['median'], digits)} / {fmt(spread['worst'], digits)}"


def _pair(first, second, digits_first: int = 3, digits_second: int = 2) -> str:
    if first is None and second is None:
        return "–"
    return f"{fmt(first, digits_first)} / {fmt(second, digits_second)}"


# the share of key frames the map contradicts (slam_engine.evaluation.consistency), median / worst seed
CONTRADICTED_COLUMN = "contradicted kf %"


def _contradicted(summary: dict) -> str:
    spread = (summary.get("map") or {}).get("contradicted_key_frames")
    if not spread or spread.get("median") is None:
        return "–"
    return f"{100 * spread['median']:.1f} / {100 * spread['worst']:.1f}"


TIMING_COLUMNS = ("particles", "seeds ok", "run s / process s", "wall s", "products s (% of wall)", "scans/s",
                  "real-time ×", "peak MB run / process")


def _timing_cells(summary: dict) -> list[str]:
    share = summary.get("products_share")
    products = fmt(summary.get("products_s"), 2) + ("" if share is None else f" ({100 * share:.0f} %)")
    return [str(summary.get("particles")), f"{summary['seeds_ok']}/{len(summary['seeds'])}",
            f"{fmt(summary.get('run_process_s'), 1)} / {fmt(summary.get('process_s'), 1)}",
            fmt(summary.get("wall_s"), 2), products,
            fmt(summary.get("scans_per_s"), 1), fmt(summary.get("realtime_factor"), 1),
            f"{fmt(summary.get('peak_run_mb'), 0)} / {fmt(summary.get('peak_memory_mb'), 0)}"]


def scored_table(summary: dict) -> Table:
    """Relation errors (median / worst seed), ATE, local and loop subsets, timing and memory."""
    table = Table(title=_title(summary), title_justify="left")
    for column in ("method", *TIMING_COLUMNS, "trans m (med / worst)", "rot ° (med / worst)", "ATE m (med / worst)",
                   "local m / °", "loop m / °", "failed rel.", CONTRADICTED_COLUMN):
        table.add_column(column, justify="left" if column == "method" else "right")
    slam = summary["slam"]
    table.add_row("RBPF SLAM", *_timing_cells(summary),
                  _median_worst(slam["trans_mean_m"], 3), _median_worst(slam["rot_mean_deg"], 2),
                  _median_worst(slam["ate_m"], 3),
                  _pair(slam["local_trans_m"]["median"], slam["local_rot_deg"]["median"]),
                  _pair(slam["loop_trans_m"]["median"], slam["loop_rot_deg"]["median"]),
                  fmt(slam["failed_relations"]["worst"], 0), _contradicted(summary))
    dr = summary["dead_reckoning"]
    table.add_row("dead reckoning", *[""] * len(TIMING_COLUMNS),
                  fmt(dr["trans_mean_m"], 3), fmt(dr["rot_mean_deg"], 2), fmt(dr["ate_m"], 3),
                  _pair(dr["local_trans_m"], dr["local_rot_deg"]), _pair(dr["loop_trans_m"], dr["loop_rot_deg"]),
                  fmt(dr["failed_relations"], 0), "")
    return table


def map_table(summary: dict) -> Table:
    """Map numbers for a log without ground truth (median / worst seed)."""
    table = Table(title=_title(summary) + " (no ground truth)", title_justify="left")
    for column in ("method", *TIMING_COLUMNS, "wall thickness m", "occupied w/ neighbour", "half agreement",
                   "half offset m", CONTRADICTED_COLUMN):
        table.add_column(column, justify="left" if column == "method" else "right")
    quality = summary["map"]
    table.add_row("RBPF SLAM", *_timing_cells(summary),
                  _median_worst(quality["wall_thickness_m"], 3), _median_worst(quality["occupied_with_neighbour"], 3),
                  _median_worst(quality["half_agreement"], 3), _median_worst(quality["half_mean_offset_m"], 3),
                  _contradicted(summary))
    dr = summary.get("dead_reckoning_map") or {}
    table.add_row("dead reckoning", *[""] * len(TIMING_COLUMNS), "", "",
                  fmt(dr.get("half_agreement"), 3), fmt(dr.get("half_mean_offset_m"), 3), "")
    return table


def _title(summary: dict) -> str:
    scans, duration = summary.get("scans"), summary.get("duration_s")
    return f"{summary['case']} — {fmt(scans)} scans, {fmt(duration, 0)} s of log"


def print_report(results: dict, console: Console | None = None) -> None:
    """Every log's table, its errors and where the files are."""
    console = console or Console()
    for summary in results["summaries"]:
        console.print(scored_table(summary) if summary["scored"] else map_table(summary))
        for seed, error in summary["errors"].items():
            last_line = (error or "").strip().splitlines()[-1:] or ["unknown error"]
            console.print(f"[red]seed {seed} failed:[/red] {last_line[0]}", highlight=False)
        if summary.get("flagged_runs"):
            console.print(f"map flagged on {summary['flagged_runs']} of {summary['seeds_ok']} runs: the back end's "
                          f"alternatives tried on {summary['flagged_retries']}, one kept on "
                          f"{summary['alternatives_kept']} (none left to try on open ground: its submap lengths "
                          "are tried on every run)", highlight=False)
        if summary["map_pngs"]:
            console.print(f"maps: {summary['map_pngs'][0]} …", highlight=False)
    console.print(f"results: {results['out_dir']}/results.json", highlight=False)
