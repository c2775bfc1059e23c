"""Each log's result against the last recorded one (``bench/recorded.json``, kept in the repository):
a regression is flagged in the table, never left for someone to notice.

The real-odometry logs broke (Intel 0.019 -> 0.357 m, Freiburg 079 0.052 -> 0.324 m) while every log
the bench printed then stayed green: nothing compared a result with the last one. A scored log is
flagged when its relation error's median over the seeds is worse than the recorded median by more
than :data:`TOLERANCE_SHARE` and :data:`TOLERANCE_M`, or when a seed loses its map (above
:data:`LOST_M`) where none did; when its absolute trajectory error's median is worse by more than
:data:`ATE_TOLERANCE_SHARE` and :data:`ATE_TOLERANCE_M` (a map bent without moving its relations:
a half drive's map 0.5 m off its ground truth read 0.027 m in relations); and every log, scored or
not, when the engine flags more of its maps as inconsistent than the record did (a map the engine
itself flags is a failure, not a result).

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
ATE_TOLERANCE_SHARE = 0.25  # an ATE median this much worse than the record (and ATE_TOLERANCE_M) is a regression:
ATE_TOLERANCE_M = 0.01      # the ATE moves more between seeds than the relations (the campus 0.53-0.77 m)
ERRORS = ("median_m", "worst_m", "ate_median_m", "ate_worst_m")  # a log's figures [m] in the record


def read_recorded(path: Path = RECORDED_PATH) -> dict:
    """The recorded results (``{"logs": {name: {"median_m", "worst_m", ...}}, ...}``), empty when none."""
    try:
        return json.loads(Path(path).read_text())
    except FileNotFoundError:
        return {}


def _measured(results: dict) -> dict[str, dict]:
    """Each log's median and worst relation error and absolute trajectory error [m] (None where it
    has no relations or ground truth), its maps the engine flagged, and its seeds, from a
    ``results.json``."""
    out = {}
    for summary in results["summaries"]:
        slam = summary.get("slam") or {}
        spread = slam.get("trans_mean_m") or {}
        ate = slam.get("ate_m") or {}
        scored = bool(summary.get("scored")) and spread.get("median") is not None
        out[summary["case"]] = {"median_m": spread["median"] if scored else None,
                                "worst_m": spread["worst"] if scored else None,
                                "ate_median_m": ate.get("median"), "ate_worst_m": ate.get("worst"),
                                "flagged_runs": int(summary.get("flagged_runs") or 0),
                                "seeds": summary["seeds"], "seeds_ok": summary["seeds_ok"]}
    return out


def _verdict(now: dict, before: dict | None) -> str:
    """``regression`` (relations, or a run failed), ``lost``, ``bent`` (ATE), ``flagged`` (more maps
    flagged), ``better``, ``as recorded`` or ``new``."""
    if now["seeds_ok"] < len(now["seeds"]):
        return "regression"  # a run failed
    if before is None:
        return "new"
    if now["flagged_runs"] > int(before.get("flagged_runs") or 0):
        return "flagged"
    median, recorded = now["median_m"], before.get("median_m")
    better = False
    if median is not None and recorded is not None:
        if now["worst_m"] > LOST_M >= before["worst_m"]:
            return "lost"
        if median > recorded * (1.0 + TOLERANCE_SHARE) + TOLERANCE_M:
            return "regression"
        better = median < recorded * (1.0 - TOLERANCE_SHARE) - TOLERANCE_M
    ate, recorded_ate = now["ate_median_m"], before.get("ate_median_m")
    if ate is not None and recorded_ate is not None and \
            ate > recorded_ate * (1.0 + ATE_TOLERANCE_SHARE) + ATE_TOLERANCE_M:
        return "bent"
    return "better" if better else "as recorded"


def compare(results: dict, recorded: dict) -> list[dict]:
    """One row per log: this run's relation error and ATE (median and worst) and flagged maps, the
    record's, the published best where known, and the verdict (:func:`_verdict`)."""
    logs = recorded.get("logs", {})
    rows = []
    for name, now in _measured(results).items():
        before = logs.get(name)
        row = {"case": name, **now, "published": PUBLISHED.get(name)}
        for key in (*ERRORS, "flagged_runs"):
            row[f"recorded_{key}"] = None if before is None else before.get(key)
        row["verdict"] = _verdict(now, before)
        rows.append(row)
    return rows


BAD_VERDICTS = ("regression", "lost", "bent", "flagged")


def regressions(rows: list[dict]) -> list[dict]:
    return [r for r in rows if r["verdict"] in BAD_VERDICTS]


def _pair(median: float | None, worst: float | None) -> str:
    return "–" if median is None else f"{fmt(median, 4)} / {fmt(worst, 4)}"


def print_regressions(rows: list[dict], recorded: dict, console: Console) -> None:
    """The comparison table, then one line saying whether anything regressed."""
    when = recorded.get("recorded", "never")
    table = Table(title=f"against the record of {when} ({RECORDED_PATH.name}; median / worst seed)",
                  title_justify="left")
    for column in ("log", "seeds", "relations m", "recorded m", "published best m", "ATE m", "recorded ATE m",
                   "flagged (recorded)", "verdict"):
        table.add_column(column, justify="left" if column in ("log", "verdict") else "right")
    for r in rows:
        published = "–" if r["published"] is None else f"{r['published'][1]:.4f} ({r['published'][0].split(' ')[0]})"
        style = "green" if r["verdict"] == "better" else "red" if r["verdict"] in BAD_VERDICTS else ""
        recorded_flagged = "–" if r["recorded_flagged_runs"] is None else r["recorded_flagged_runs"]
        table.add_row(r["case"], f"{r['seeds_ok']}/{len(r['seeds'])}", _pair(r["median_m"], r["worst_m"]),
                      _pair(r["recorded_median_m"], r["recorded_worst_m"]), published,
                      _pair(r["ate_median_m"], r["ate_worst_m"]),
                      _pair(r["recorded_ate_median_m"], r["recorded_ate_worst_m"]),
                      f"{r['flagged_runs']} ({recorded_flagged})",
                      f"[{style}]{r['verdict']}[/{style}]" if style else r["verdict"])
    console.print(table)
    bad = regressions(rows)
    if bad:
        console.print(f"[red]REGRESSION[/red] against the record: {', '.join(r['case'] for r in bad)}", highlight=False)
    else:
        console.print("no regression against the record", highlight=False)


def _rounded(value: float | None) -> float | None:
    return None if value is None else round(value, 5)


def record(results: dict, path: Path = RECORDED_PATH) -> dict:
    """Write this run's logs (relation error and ATE, median and worst; flagged maps; seeds) as the
    record, keeping logs it did not run."""
    recorded = read_recorded(path)
    logs = dict(recorded.get("logs", {}))
    for name, now in _measured(results).items():
        logs[name] = {key: _rounded(now[key]) for key in ERRORS}
        logs[name].update(flagged_runs=now["flagged_runs"], seeds=now["seeds"])
    out = {"recorded": time.strftime("%Y-%m-%d"), "code": results.get("code"),
           "options": {k: results["options"].get(k) for k in ("particles", "config")},
           "logs": dict(sorted(logs.items()))}
    Path(path).write_text(json.dumps(out, indent=1) + "\n")
    return out
