"""``python -m bench margin``: each (log, seed) in its own process with the stand-in engine of
``test_bench`` (its trajectory: the odometry stretched by 5 % per seed, so the error grows with the
seed), a map counted lost above ``LOST_M`` or when its run failed, and the table printed from it."""

from __future__ import annotations

import json

import pytest
from rich.console import Console

from bench.cases import cases_for_path
from bench.harness import BenchOptions
from bench.margin import LOST_M, RESULTS_FILE, margin_row, print_margin, run_margin
from tests.bench.test_bench import FAKE_ENGINE, write_case


@pytest.fixture(scope="module")
def margin_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("margin")
    (root / "fake_engine.py").write_text(FAKE_ENGINE)
    cases = cases_for_path(write_case(root / "sparse"))
    options = BenchOptions(seeds=[0, 2, 6], particles=5, runner="fake_engine:run_slam",
                           extra_pythonpath=[str(root)], out_dir=root / "out")
    lines: list[str] = []
    results = run_margin(cases, options, say=lines.append)
    options.runner, options.out_dir, options.seeds = "fake_engine:broken", root / "broken", [0]
    broken = run_margin(cases, options, say=lines.append)
    return root, results, broken, lines


def test_every_seed_is_scored_and_lost_above_the_bar(margin_runs) -> None:
    root, results, _, lines = margin_runs
    (row,) = results["rows"]
    per_seed = [json.loads((root / "out" / f"{row['log']}_seed{seed}.json").read_text())
                for seed in (0, 2, 6)]
    errors = [run["slam"]["relations"]["all"]["trans_mean_m"] for run in per_seed]
    assert row["errors_m"] == pytest.approx(errors) and errors[0] < errors[1] < errors[2]
    assert all(run["particles"] == 5 for run in per_seed)
    assert row["lost_seeds"] == [s for s, e in zip((0, 2, 6), errors, strict=True) if e > LOST_M]
    assert row["lost_seeds"] == [6]  # measured: 0.021, 0.071 and 0.181 m
    assert row["lost"] == len(row["lost_seeds"]) and row["runs"] == 3
    assert row["median_m"] == pytest.approx(errors[1]) and row["worst_m"] == pytest.approx(errors[2])
    assert json.loads((root / "out" / RESULTS_FILE).read_text())["rows"] == results["rows"]
    assert len(lines) == 4 and lines[0].endswith(f"{errors[0]:.3f} m") and lines[-1].endswith("failed")


def test_a_failed_run_counts_as_lost(margin_runs) -> None:
    _, _, broken, _ = margin_runs
    (row,) = broken["rows"]
    assert row["errors_m"] == [None] and row["lost"] == 1 and row["median_m"] is None


def test_the_table_shows_each_log_and_seed(margin_runs) -> None:
    _, results, broken, _ = margin_runs
    console = Console(record=True, width=200)
    print_margin(results, console)
    print_margin(broken, console)
    text = console.export_text()
    row = results["rows"][0]
    assert f"{row['lost']} of 3" in text and f"{row['worst_m']:.3f}" in text and "1 of 1" in text
    assert ", ".join(f"{e:.3f}" for e in row["errors_m"]) in text and "failed" in text


def test_margin_row_counts_failures_and_errors_above_the_bar() -> None:
    ok = {"status": "ok", "slam": {"relations": {"all": {"trans_mean_m": 0.04}}}}
    bad = {"status": "ok", "slam": {"relations": {"all": {"trans_mean_m": 0.5}}}}
    row = margin_row("log", [{**ok, "seed": 0}, {**bad, "seed": 1}, {"status": "error", "seed": 2}])
    assert row["lost_seeds"] == [1, 2] and row["median_m"] == pytest.approx(0.27) and row["worst_m"] == 0.5
