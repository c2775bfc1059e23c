"""``python -m bench.which_map``: every drive given the same saved maps is placed in its own building's, and
a drive from a building none of them holds is refused by all."""

from __future__ import annotations

import pytest

from bench.which_map import measure, table

pytestmark = pytest.mark.slow


def test_each_drive_is_placed_in_its_own_floors_map_and_a_foreign_one_in_none() -> None:
    said: list[str] = []
    rows = measure(0, n_maps=2, say=said.append, shared=False)
    by_drive = {r["drive"]: r for r in rows}
    assert set(by_drive) == {"building-1-back", "building-2-back", "office", "building-3"}
    for name in ("building-1-back", "building-2-back"):
        row = by_drive[name]
        assert row["chosen"] == name.removesuffix("-back") and row["right"] and row["home_rank"] == 1, row
        assert row["tried"] == 1 and row["time_ratio"] == pytest.approx(row["wall_s"] / row["one_map_s"])
    for name in ("office", "building-3"):
        assert by_drive[name]["chosen"] is None and by_drive[name]["right"] and by_drive[name]["tried"] == 2
    assert len(said) == 4 and "building-1-back among 2 maps: building-1 (right; tried 1" in said[0]
    text = table(rows, 2).splitlines()
    assert text[2].startswith("| building-1-back | building-1 | 1/1 | 1 | 1 | ")
    assert text[4].startswith("| office | none (refused) | 1/1 | - | 2 | ")
    assert text[-1].startswith("right 4 of 4; time ratio median ")
