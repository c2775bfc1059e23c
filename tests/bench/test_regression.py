"""The bench compares every scored log with the last recorded result and flags what got worse
(``bench/regression.py``), and runs the original real-odometry logs beside the benchmark's own."""

from __future__ import annotations

from rich.console import Console

from bench.cases import default_cases
from bench.regression import compare, print_regressions, read_recorded, record, regressions


def _results(**medians_and_worst: tuple[float, float]) -> dict:
    return {"code": {"commit": "abc", "dirty": False}, "options": {"particles": None, "config": {}},
            "summaries": [{"case": name, "scored": True, "seeds": [0, 1, 2], "seeds_ok": 3,
                           "slam": {"trans_mean_m": {"median": median, "worst": worst}}}
                          for name, (median, worst) in medians_and_worst.items()]}


RECORDED = {"recorded": "2026-11-26", "logs": {"real-intel": {"median_m": 0.0189, "worst_m": 0.0205},
                                               "real-fr079": {"median_m": 0.0523, "worst_m": 0.060},
                                               "intel": {"median_m": 0.021, "worst_m": 0.022}}}


def test_the_broken_real_logs_would_have_been_flagged() -> None:
    """2026-11-28's figures against 2026-11-26's: real Intel 0.357 m (a map lost), Freiburg 079 worse."""
    rows = {r["case"]: r for r in compare(_results(**{"real-intel": (0.357, 0.40), "real-fr079": (0.070, 0.08),
                                                      "intel": (0.0215, 0.0220), "aces-rough": (0.04, 0.041)}),
                                          RECORDED)}
    assert rows["real-intel"]["verdict"] == "lost"
    assert rows["real-fr079"]["verdict"] == "regression"
    assert rows["intel"]["verdict"] == "as recorded"  # within 10 % and 1 mm
    assert rows["aces-rough"]["verdict"] == "new"
    assert rows["real-intel"]["published"][1] == 0.0229
    assert [r["case"] for r in regressions(list(rows.values()))] == ["real-intel", "real-fr079"]
    console = Console(width=200, record=True)
    print_regressions(list(rows.values()), RECORDED, console)
    assert "REGRESSION against the record: real-intel, real-fr079" in console.export_text()


def test_a_better_result_is_said_and_can_become_the_record(tmp_path) -> None:
    rows = compare(_results(**{"real-fr079": (0.045, 0.047)}), RECORDED)
    assert rows[0]["verdict"] == "better" and regressions(rows) == []
    path = tmp_path / "recorded.json"
    path.write_text('{"logs": {"intel": {"median_m": 0.021, "worst_m": 0.022, "seeds": [0]}}}')
    written = record(_results(**{"real-fr079": (0.0466, 0.0478)}), path)
    assert read_recorded(path) == written
    assert written["logs"]["real-fr079"] == {"median_m": 0.0466, "worst_m": 0.0478, "seeds": [0, 1, 2]}
    assert "intel" in written["logs"]  # logs this run did not map keep their record


def test_a_failed_run_is_a_regression() -> None:
    results = _results(intel=(0.021, 0.022))
    results["summaries"][0]["seeds_ok"] = 2
    assert compare(results, RECORDED)[0]["verdict"] == "regression"


def test_the_real_odometry_logs_are_benchmarked_beside_the_others(dataset) -> None:
    dataset("real/intel.clf.gz")
    cases = {c.name: c for c in default_cases(map_only=False)}
    assert {"real-intel", "real-fr079", "intel", "freiburg-079"} <= set(cases)
    assert cases["real-intel"].relations_path.endswith("real/intel.relations")
    assert read_recorded()["logs"]["real-intel"]["median_m"] < 0.020  # the record holds the real logs
