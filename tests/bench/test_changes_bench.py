"""``python -m bench.changes``: the change map scored against the simulated office's known changes."""

from __future__ import annotations

import pytest

from bench.changes import TARGETS, measure, table

pytestmark = pytest.mark.slow


def test_the_simulated_changes_are_found_and_the_unchanged_office_shows_none() -> None:
    row = measure(3)
    changed, unchanged = row["office-changed"], row["office"]
    assert changed["localised"] and unchanged["localised"]
    assert changed["precision"] >= TARGETS["precision"] and changed["recall"] >= TARGETS["recall"], changed
    assert 0.002 < changed["share"] < 0.02 and unchanged["share"] <= 0.001
    assert changed["time_ratio"] == pytest.approx(changed["changes_s"] / changed["localise_s"])
    text = table([row])
    assert text.splitlines()[2].startswith("| 3 | ") and f"{changed['precision']:.3f}" in text
    assert text.splitlines()[3].startswith("| median | ") and "precision >= 0.9, recall >= 0.8" in text
