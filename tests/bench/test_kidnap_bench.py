"""``python -m bench.kidnap``: a robot carried off in a made-up floor is noticed lost within metres and never
reported found where it is not."""

from __future__ import annotations

import pytest

from bench.kidnap import measure, table

pytestmark = pytest.mark.slow


def test_a_kidnapped_robot_is_lost_within_metres_and_never_found_wrong() -> None:
    row = measure(2)
    assert row["building"] == "building-2" and row["jump_m"] > 5.0
    assert row["lost_after_m"] is not None and row["lost_after_m"] < 3.0 and row["wrong"] == 0
    assert row["found_after_m"] is None or row["lost_after_m"] < row["found_after_m"] <= row["driven_after_m"]
    text = table([row]).splitlines()
    assert text[2].startswith(f"| building-2 | {row['jump_m']:.1f} | {row['lost_after_m']:.1f} | ")
    assert row["foreign_scans"] > 300 and 0 <= row["foreign_found"] <= row["foreign_scans"]
    assert f"| {row['foreign_found']} of {row['foreign_scans']} |" in text[2]
    assert "confidently wrong scans 0 (target 0); the next floor's drive found in " in text[-1]
