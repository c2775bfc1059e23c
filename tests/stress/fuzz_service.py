"""Fuzz the service through its own OpenAPI schema with schemathesis, in-process (ASGI).

Every operation gets generated requests, valid ones (positive) and invalid ones (negative); path
ids are swapped, half of the time, for real ones (a session with an upload and a finished mapping
job, a streaming session) so the fuzz reaches past the 404s into uploads, chunks, jobs, products
and tiles. Each answer is checked for: no server error (5xx), a status code the schema documents,
a content type and a body that match the schema.

    python -m tests.stress.fuzz_service --cases 1000 --seed 1

The data folder is prepared with one real mapping job (the service on the real job function),
then the service is restarted on the same folder with a job function that finishes at once, so
the many jobs the fuzz creates cost nothing.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
if str(HERE) not in sys.path:  # the spawned workers import the injected job function by name
    sys.path.insert(0, str(HERE))

INSTANT_JOB = "stress_jobs:instant"
ID_PARAMETERS = ("session_id", "job_id")
MAX_FAILURES_KEPT = 20
MAX_ROUNDS = 10


@dataclass
class FuzzReport:
    """What the fuzz sent and what broke."""

    cases: int = 0
    operations: int = 0
    server_errors: int = 0
    undocumented_status: int = 0
    schema_violations: int = 0
    statuses: Counter = field(default_factory=Counter)
    per_operation: Counter = field(default_factory=Counter)
    failures: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return self.server_errors == 0 and self.undocumented_status == 0 and self.schema_violations == 0

    def table(self) -> str:
        statuses = ", ".join(f"{code}: {n}" for code, n in sorted(self.statuses.items(), key=str))
        rows = [("generated cases", self.cases), ("operations fuzzed", self.operations),
                ("server errors (5xx)", self.server_errors),
                ("undocumented status codes", self.undocumented_status),
                ("schema-violating responses", self.schema_violations),
                ("wall time [s]", f"{self.seconds:.1f}"), ("statuses seen", statuses)]
        width = max(len(name) for name, _ in rows)
        return "\n".join(f"{name:<{width}}  {value}" for name, value in rows)


def tiny_log(out_dir: Path) -> Path:
    """A short simulated CARMEN log (40 scans): a real mapping job on it takes about a second."""
    from slam_engine.simulation import simulate, write_simulated

    drive = simulate("office", seed=1, rig="carmen-robot", max_duration_s=8.0)
    return write_simulated(drive, "carmen", out_dir)


@dataclass
class KnownIds:
    """Real ids the fuzz swaps into path parameters."""

    session_id: list[str]
    job_id: list[str]


def prepare(data_dir: Path, log_path: Path) -> KnownIds:
    """Sessions, an upload, streamed chunks and one real finished mapping job in ``data_dir``."""
    from schemathesis.python import asgi

    from service.api.app import create_app
    from service.settings import Settings
    from service.storage.stream_log import calibration_from_log, messages_of_log
    from slam_engine.formats import load_log

    app = create_app(Settings(data_dir=data_dir, workers=1))
    with asgi.get_client(app) as client:
        mapped = _ok(client.post("/v1/sessions", json={"name": "fuzz: uploaded"}))["id"]
        with log_path.open("rb") as f:
            _ok(client.post(f"/v1/sessions/{mapped}/logs", files={"file": (log_path.name, f)}))
        job = _ok(client.post(f"/v1/sessions/{mapped}/jobs", json={"particles": 3, "resolution_m": 0.2,
                                                                   "snapshot_every_scans": 10}))["id"]
        log = load_log(log_path)
        streamed = _ok(client.post("/v1/sessions", json={"name": "fuzz: streamed",
                                                         "calibration": calibration_from_log(log)}))["id"]
        messages = messages_of_log(log)
        for seq in range(3):
            _ok(client.post(f"/v1/sessions/{streamed}/chunks",
                            json={"seq": seq, "messages": messages[seq * 20:(seq + 1) * 20]}))
        deadline = time.monotonic() + 300
        while (status := client.get(f"/v1/jobs/{job}").json()["status"]) in ("queued", "running"):
            if time.monotonic() > deadline:
                raise RuntimeError("the preparatory mapping job did not finish in 300 s")
            time.sleep(0.1)
        if status != "succeeded":
            raise RuntimeError(f"the preparatory mapping job ended {status}: {client.get(f'/v1/jobs/{job}').text}")
    asgi.shutdown_lifespans()
    return KnownIds(session_id=[mapped, streamed], job_id=[job])


def _ok(response) -> dict[str, Any]:
    if response.status_code >= 300:
        raise RuntimeError(f"{response.request.method} {response.request.url}: {response.status_code} {response.text}")
    return response.json()


def _checks() -> list:
    from schemathesis.checks import not_a_server_error
    from schemathesis.specs.openapi.checks import (
        content_type_conformance,
        response_headers_conformance,
        response_schema_conformance,
        status_code_conformance,
    )

    return [not_a_server_error, status_code_conformance, content_type_conformance, response_headers_conformance,
            response_schema_conformance]


def _classify(report: FuzzReport, label: str, failures: list) -> None:
    for failure in failures:
        name = type(failure).__name__
        if name == "ServerError":
            report.server_errors += 1
        elif name == "UndefinedStatusCode":
            report.undocumented_status += 1
        else:
            report.schema_violations += 1
        if len(report.failures) < MAX_FAILURES_KEPT:
            report.failures.append(f"{label}: {name}: {failure.title} -- {failure.message[:400]}")


def fuzz_service(cases: int, seed: int, data_dir: Path, log_path: Path | None = None,
                 prepared: bool = True) -> FuzzReport:
    """Send at least ``cases`` generated requests to a service on ``data_dir``; the report counts
    the failed checks. ``prepared`` first maps ``log_path`` (a tiny simulated log by default)."""
    import schemathesis
    from schemathesis.generation import GenerationMode
    from schemathesis.python import asgi

    from service.api.app import create_app
    from service.settings import Settings

    t0 = time.monotonic()
    known = KnownIds(session_id=[], job_id=[])
    if prepared:
        known = prepare(data_dir, log_path or tiny_log(data_dir.parent / "fuzz-log"))
    app = create_app(Settings(data_dir=data_dir, workers=1, max_upload_bytes=1024**2, max_chunk_bytes=256 * 1024,
                              cancel_grace_s=0.5), job_function=INSTANT_JOB)
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    operations = [result.ok() for result in schema.get_all_operations()]
    report = FuzzReport(operations=len(operations))
    checks = _checks()
    with asgi.get_client(app) as client:
        for round_ in range(MAX_ROUNDS):  # operations with few distinct inputs run dry: top up with new seeds
            missing = cases - report.cases
            if missing <= 0:
                break
            per_run = max(1, math.ceil(missing / (2 * len(operations))))
            for operation in operations:
                label = f"{operation.method.upper()} {operation.path}"
                for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE):
                    strategy = operation.as_strategy(generation_mode=mode)
                    _fuzz_operation(strategy, label, per_run, seed + round_, known, client, checks, report)
    asgi.shutdown_lifespans()
    report.seconds = time.monotonic() - t0
    return report


def _fuzz_operation(strategy, label: str, examples: int, seed: int, known: KnownIds, client, checks: list,
                    report: FuzzReport) -> None:
    """``examples`` generated cases of one operation, sent and checked; failures go to ``report``."""
    import hypothesis
    from hypothesis import strategies as st
    from schemathesis.core.failures import FailureGroup

    @hypothesis.seed(seed)
    @hypothesis.settings(max_examples=examples, deadline=None, database=None, phases=[hypothesis.Phase.generate],
                         suppress_health_check=list(hypothesis.HealthCheck))
    @hypothesis.given(case=strategy, data=st.data())
    def one(case, data) -> None:
        _swap_ids(case, data, known, client)
        report.cases += 1
        report.per_operation[label] += 1
        try:
            response = case.call()
        except Exception as exc:  # the in-process client re-raises what the app did not handle
            report.server_errors += 1
            report.statuses["exception"] += 1
            if len(report.failures) < MAX_FAILURES_KEPT:
                report.failures.append(f"{label}: unhandled {type(exc).__name__}: {exc} -- {case.as_curl_command()}")
            return
        report.statuses[response.status_code] += 1
        try:
            case.validate_response(response, checks=checks)
        except FailureGroup as group:
            _classify(report, f"{label} -> {response.status_code} {response.text[:200]!r}", list(group.exceptions))

    # Unsatisfiable: no invalid request exists (e.g. negative cases of an operation without parameters)
    with contextlib.suppress(hypothesis.errors.Unsatisfiable):
        one()


def _swap_ids(case, data, known: KnownIds, client) -> None:
    """Half of the time, a real id for each id parameter; DELETE gets a throwaway session so the
    real ones survive the fuzz."""
    for name in ID_PARAMETERS:
        if not case.path_parameters or name not in case.path_parameters:
            continue
        if not data.draw(_coin(), label=f"real {name}"):
            continue
        if case.method.upper() == "DELETE" and name == "session_id":
            throwaway = client.post("/v1/sessions", json={"name": "fuzz: throwaway"}).json()["id"]
            case.path_parameters[name] = throwaway
        elif getattr(known, name):
            case.path_parameters[name] = data.draw(_sampled(getattr(known, name)), label=name)


def _coin():
    from hypothesis import strategies as st

    return st.booleans()


def _sampled(values: list[str]):
    from hypothesis import strategies as st

    return st.sampled_from(values)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", type=int, default=1000, help="at least this many generated requests")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="lidarmap-fuzz-") as tmp:
        report = fuzz_service(args.cases, args.seed, Path(tmp) / "data")
    print(report.table())
    for line in report.failures:
        print("FAIL", line)
    return 0 if report.ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
