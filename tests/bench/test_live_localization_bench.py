"""``python -m bench.live_localization`` on a short setup: a real service, the office's first 40 s mapped and
driven again at 4x real time (no busy process), a foreign drive's 30 s beside it; the figures checked
against the reports they come from and against the simulator's truth (no assertion on speed)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from rich.console import Console

from bench.live_localization import RESULTS_FILE, main, run_live_localization_table

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def bench_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("live-localization")
    console = Console(record=True, width=250)
    results = run_live_localization_table(out, console, busy=0, speed=4.0, drive_s=40.0, map_s=40.0, foreign_s=30.0)
    return results, json.loads((out / RESULTS_FILE).read_text()), console.export_text()


def test_every_scan_is_reported_once_in_order_with_its_latency(bench_run) -> None:
    results, written, _ = bench_run
    assert written["office"]["poses"] == results["office"]["poses"] and len(written["code"]["commit"]) == 40
    for name in ("office", "foreign"):
        row = results[name]
        assert row["status"] == "succeeded" and row["in_order"], (name, row["error"])
        poses = row["poses"]
        assert [p["scan"] for p in poses] == list(range(row["scans"])) and row["reports"] == row["scans"] > 100
        assert all(p["read_s"] is not None and p["read_s"] >= 0 for p in poses)
        latencies = [p["latency_s"] for p in poses if p["latency_s"] is not None]
        assert len(latencies) == row["scans"] - row["unplaced_at_end"] >= row["scans"] - 2
        assert min(latencies) >= 0 and row["latency_s"]["count"] == len(latencies)
        assert row["latency_s"]["p95"] == pytest.approx(np.percentile(latencies, 95))
        assert 0 <= row["latency_s"]["p50"] <= row["latency_s"]["p95"] <= row["latency_s"]["p99"] \
            <= row["latency_s"]["max"] == max(latencies)
        assert row["client_latency_s"]["max"] == pytest.approx(max(p["read_s"] for p in poses), abs=1e-3)
        assert len(row["backlog"]) == row["chunks"] - 1 and 0 <= row["backlog_median"] <= row["backlog_max"]
        assert row["localization"]["scans"] == row["scans"]  # run.json of the finished job


def test_the_office_is_found_where_the_robot_is(bench_run) -> None:
    office = bench_run[0]["office"]
    states = [p["state"] for p in office["poses"]]
    first = states.index("found")
    assert set(states[:first]) == {"searching"} and office["first_found_scan"] == first
    assert office["found"] == states.count("found") >= 0.9 * (len(states) - first)
    assert office["found_share_after_first"] == pytest.approx(states[first:].count("found") / (len(states) - first))
    errors = [p["error_m"] for p in office["poses"] if p["state"] == "found"]
    assert None not in errors and max(errors) == pytest.approx(office["error_max_m"], abs=1e-5) and max(errors) < 0.1
    assert 0 < office["first_found_drive_s"] <= office["drive_s"] and office["first_found_travel_m"] > 0
    assert office["first_found_travel_m"] == pytest.approx(office["localization"]["first_found_travel_m"], abs=0.5)
    assert office["localization"]["states"]["found"] == office["found"]


def test_the_foreign_drive_is_never_found(bench_run) -> None:
    foreign = bench_run[0]["foreign"]
    assert foreign["found"] == 0 and not foreign["localization"]["localised"]
    assert all(p["state"] != "found" and p["error_m"] is None for p in foreign["poses"])
    assert foreign["first_found_drive_s"] is None and foreign["localization"]["states"]["found"] == 0


def test_the_table_has_every_row(bench_run) -> None:
    results, _, text = bench_run
    for row in ("chunk accepted to pose written", "the client sees", "backlog before each chunk",
                "first confident (found) pose", "scans found after the first found",
                "found poses against the ground truth", "foreign drive (campus robot, seed 1, 30 s"):
        assert row in text, row
    office = results["office"]
    assert f"{1000 * office['latency_s']['p95']:.0f} ms" in text and "| <= 100 ms |" in text
    assert f"| never | 0 (states {results['foreign']['states']}) | met |" in text


@pytest.mark.parametrize("flags", [["--speed", "0"], ["--busy", "-1"], ["--chunk-s", "0"], ["--foreign-s", "1"]])
def test_bad_options_are_refused(flags, tmp_path) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main([*flags, "--out", str(tmp_path)])
    assert exit_info.value.code == 2
    assert not (tmp_path / RESULTS_FILE).exists()
