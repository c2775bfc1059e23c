"""A small, deterministic run of the schema fuzzer (tests/stress/fuzz_service.py): generated valid
and invalid requests to every route, no 5xx, no undocumented status, no schema-violating answer.
The full run (1000+ cases) is ``python -m tests.stress.fuzz_service``."""

from __future__ import annotations

from fuzz_service import fuzz_service  # schemathesis is a dev dependency: missing, this fails, never skips


def test_fuzzed_requests_get_documented_answers(tmp_path) -> None:
    report = fuzz_service(cases=100, seed=11, data_dir=tmp_path / "data")
    print(report.table())
    assert report.cases >= 100 and report.operations >= 26
    assert report.ok, "\n".join(report.failures)
    assert report.statuses[200] > 0 and report.statuses[422] > 0 and report.statuses[404] > 0
    # the fuzz got past the ids: real sessions and jobs answered
    assert sum(report.statuses[s] for s in (201, 202, 409)) > 0
