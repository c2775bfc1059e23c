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
    assert written["logs"]["real-fr079"] == {"median_m": 0.0466, "worst_m": 0.0478, "ate_median_m": None,
                                             "ate_worst_m": None, "flagged_runs": 0, "seeds": [0, 1, 2]}
    assert "intel" in written["logs"]  # logs this run did not map keep their record


def test_a_map_bent_without_moving_its_relations_is_a_regression() -> None:
    """A half drive's map 0.5 m off its ground truth read 0.027 m in relations: the ATE is guarded too,
    with more room than the relations (it moves more between seeds)."""
    recorded = {"logs": {"intel": {"median_m": 0.021, "worst_m": 0.022, "ate_median_m": 0.048, "ate_worst_m": 0.052}}}

    def verdict(ate_median: float) -> str:
        results = _results(intel=(0.021, 0.022))
        results["summaries"][0]["slam"]["ate_m"] = {"median": ate_median, "worst": ate_median + 0.01}
        return compare(results, recorded)[0]["verdict"]

    assert verdict(0.060) == "as recorded"  # 0.048 * 1.25 + 0.01 = 0.07 allowed
    assert verdict(0.075) == "bent"
    rows = compare(_results(intel=(0.021, 0.022)), recorded)  # a run without ground truth: relations only
    assert rows[0]["verdict"] == "as recorded" and rows[0]["recorded_ate_median_m"] == 0.048


def test_more_maps_flagged_than_recorded_is_a_regression_scored_or_not() -> None:
    """A map the engine itself flags as inconsistent is a failure, also on a log without relations."""
    recorded = {"logs": {"intel": {"median_m": 0.021, "worst_m": 0.022, "flagged_runs": 0},
                         "malaga": {"median_m": None, "worst_m": None, "flagged_runs": 2}}}
    results = _results(intel=(0.021, 0.022))
    results["summaries"][0]["flagged_runs"] = 1
    results["summaries"].append({"case": "malaga", "scored": False, "seeds": [0, 1, 2], "seeds_ok": 3,
                                 "slam": {"trans_mean_m": {"median": None, "worst": None}}, "flagged_runs": 2})
    rows = {r["case"]: r for r in compare(results, recorded)}
    assert rows["intel"]["verdict"] == "flagged" and rows["malaga"]["verdict"] == "as recorded"
    assert [r["case"] for r in regressions(list(rows.values()))] == ["intel"]
    results["summaries"][1]["flagged_runs"] = 3
    assert compare(results, recorded)[1]["verdict"] == "flagged"
    console = Console(width=250, record=True)
    print_regressions(compare(results, recorded), recorded, console)
    text = console.export_text()
    assert "REGRESSION against the record: intel, malaga" in text and "3 (2)" in text


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
