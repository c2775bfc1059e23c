"""Shared fixtures: where the shared datasets are, and how their absence is handled.

Datasets are found as the benchmark finds them (``bench.cases.datasets_root``): ``LIDARMAP_DATASETS``
or ``../shared/datasets`` beside the checkout.
When missing, tests that need them skip with the reason; with ``CI=true`` they fail instead, so CI
never silently skips the real-data tests.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from bench.cases import datasets_root


def require_dataset(relative: str) -> Path:
    """Path of ``relative`` inside the datasets folder, or skip (fail on CI) when it is missing."""
    path = datasets_root() / relative
    if not path.exists():
        reason = (f"dataset {relative!r} not found under {datasets_root()} "
                  "(set LIDARMAP_DATASETS to the shared datasets folder)")
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(reason)
        pytest.skip(reason)
    return path


@pytest.fixture
def dataset():
    """``dataset("benchmark/intel.clf")`` -> Path, skipping (or failing on CI) when absent."""
    return require_dataset
