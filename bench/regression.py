"""Each scored log's relation error against the last recorded result (``bench/recorded.json``, kept in
the repository): a regression is flagged in the table, never left for someone to notice.

The real-odometry logs broke (Intel 0.019 -> 0.357 m, Freiburg 079 0.052 -> 0.324 m) while every log
the bench printed then stayed green: nothing compared a result with the last one. A log is flagged
when its median over the seeds is worse than the recorded median by more than :data:`TOLERANCE_SHARE`
and :data:`TOLERANCE_M`, or when a seed loses its map (above :data:`LOST_M`) where none did.

``python -m bench --record`` writes the run's medians and worst seeds as the new record.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from bench.cases import PUBLISHED, REPO_ROOT
from bench.report import fmt

RECORDED_PATH = REPO_ROOT / "bench" / "recorded.json"
TOLERANCE_SHARE = 0.10  # a median this much worse than the record (and TOLERANCE_M) is a regression
TOLERANCE_M = 0.001
LOST_M = 0.10  # a seed above this relation error [m] has lost its map


def read_recorded(path: Path = RECORDED_PATH) -> dict:
    """The recorded results (``{"logs": {name: {"median_m", "worst_m", ...}}, ...}``), empty when none."""
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        return {}


def _scored(results: dict) -> dict[str, dict]:
    """Each scored log's median and worst relation error [m] and its seeds, from a ``results.json``."""
    out = {}
    for summary in results["summaries"]:
        spread = (summary.get("slam") or {}).get("trans_mean_m") or {}
        if summary.get("scored") and spread.get("median") is not None:
            out[summary["case"]] = {"median_m": spread["median"], "worst_m": spread["worst"],
                                    "seeds": summary["seeds"], "seeds_ok": summary["seeds_ok"]}
    return out


def compare(results: dict, recorded: dict) -> list[dict]:
    """One row per scored log: this run's median and worst, the record's, the published best where
    known, and the verdict (``regression``, ``lost``, ``better``, ``as recorded``, ``new``)."""
    logs = recorded.get("logs", {})
    rows = []
    for name, now in _scored(results).items():
        before = logs.get(name)
        row = {"case": name, **now, "recorded_median_m": None, "recorded_worst_m": None,
               "published": PUBLISHED.get(name)}
        if now["seeds_ok"] < len(now["seeds"]):
            verdict = "regression"  # a run failed
        elif before is None:
            verdict = "new"
        else:
            row["recorded_median_m"], row["recorded_worst_m"] = before["median_m"], before["worst_m"]
            allowed = before["median_m"] * (1.0 + TOLERANCE_SHARE) + TOLERANCE_M
            if now["worst_m"] > LOST_M >= before["worst_m"]:
                verdict = "lost"
            elif now["median_m"] > allowed:
                verdict = "regression"
            elif now["median_m"] < before["median_m"] * (1.0 - TOLERANCE_SHARE) - TOLERANCE_M:
                verdict = "better"
            else:
                verdict = "as recorded"
        row["verdict"] = verdict
        rows.append(row)
    return rows


def regressions(rows: list[dict]) -> list[dict]:
    return [r for r in rows if r["verdict"] in ("regression", "lost")]


def print_regressions(rows: list[dict], recorded: dict, console: Console) -> None:
    """The comparison table, then one line saying whether anything regressed."""
    when = recorded.get("recorded", "never")
    table = Table(title=f"relation error against the record of {when} ({RECORDED_PATH.name}; median / worst seed)",
                  title_justify="left")
    for column in ("log", "seeds", "now m", "recorded m", "published best m", "verdict"):
        table.add_column(column, justify="left" if column in ("log", "verdict") else "right")
    for r in rows:
        published = "–" if r["published"] is None else f"{r['published'][1]:.4f} ({r['published'][0].split(' ')[0]})"
        style = {"regression": "red", "lost": "red", "better": "green"}.get(r["verdict"], "")
        recorded_cell = "–" if r["recorded_median_m"] is None else \
            f"{fmt(r['recorded_median_m'], 4)} / {fmt(r['recorded_worst_m'], 4)}"
        now_cell = f"{fmt(r['median_m'], 4)} / {fmt(r['worst_m'], 4)}"
        table.add_row(r["case"], f"{r['seeds_ok']}/{len(r['seeds'])}", now_cell, recorded_cell, published,
                      f"[{style}]{r['verdict']}[/{style}]" if style else r["verdict"])
    console.print(table)
    bad = regressions(rows)
    if bad:
        console.print(f"[red]REGRESSION[/red] against the record: {', '.join(r['case'] for r in bad)}", highlight=False)
    else:
        console.print("no regression against the record", highlight=False)


def record(results: dict, path: Path = RECORDED_PATH) -> dict:
    """Write this run's scored logs (median, worst, seeds) as the record, keeping logs it did not run."""
    recorded = read_recorded(path)
    logs = dict(recorded.get("logs", {}))
    for name, now in _scored(results).items():
        logs[name] = {"median_m": round(now["median_m"], 5), "worst_m": round(now["worst_m"], 5),
                      "seeds": now["seeds"]}
    out = {"recorded": time.strftime("%Y-%m-%d"), "code": results.get("code"),
           "options": {k: results["options"].get(k) for k in ("particles", "config")},
           "logs": dict(sorted(logs.items()))}
    Path(path).write_text(json.dumps(out, indent=1) + "\n")
    return out
