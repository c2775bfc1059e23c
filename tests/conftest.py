"""Shared fixtures: where the shared datasets are, and how their absence is handled.

Datasets are found as the benchmark finds them (``bench.cases.datasets_root``): ``LIDARMAP_DATASETS``
or ``../shared/datasets`` beside the checkout.
When missing, tests that need them skip with the reason; with ``CI=true`` they fail instead, so CI
never silently skips the real-data tests. Every other skip for a missing capability (a tmpfs mount,
a second numba thread) goes through ``ci_skips.skip_or_fail_on_ci`` too.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from ci_skips import skip_or_fail_on_ci
from postgres_server import running_postgres

from bench.cases import datasets_root


def require_dataset(relative: str) -> Path:
    """Path of ``relative`` inside the datasets folder, or skip (fail on CI) when it is missing."""
    path = datasets_root() / relative
    if not path.exists():
        skip_or_fail_on_ci(f"dataset {relative!r} not found under {datasets_root()} "
                           "(set LIDARMAP_DATASETS to the shared datasets folder)")
    return path


@pytest.fixture
def dataset():
    """``dataset("benchmark/intel.clf")`` -> Path, skipping (or failing on CI) when absent."""
    return require_dataset


@pytest.fixture(scope="module")
def postgres():
    """A throw-away PostgreSQL server (``postgres_server.running_postgres``): loopback only, stopped
    and deleted after the module's tests; skipped (failed on CI) where the binaries are missing."""
    with running_postgres() as server:
        yield server
