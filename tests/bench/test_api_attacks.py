"""``python -m bench.api_attacks`` at a small size: every attack runs against a real service and is
answered as it should be (tiles and trajectories 200, the header 431), and the table is printed."""

from __future__ import annotations

from bench.api_attacks import MB, main, three_far_scans_log


def test_the_attack_table_at_a_small_size(capsys) -> None:
    rows = main(poses=2000, header_mb=1, tiles=False, grid_cells=700)
    names = [name for name, _ in rows]
    assert len(rows) == 6 and "one 1 MB header" in names
    for name, cost in rows:
        assert set(cost.statuses) == ({431} if "header" in name else {200}), (name, cost.statuses)
        assert 0 < cost.rss_before <= cost.rss_peak < 600 * MB
    table = capsys.readouterr().out.splitlines()
    assert table[0].startswith("| attack | statuses | API RSS before [MB] | API peak RSS [MB]") and len(table) == 8


def test_the_probes_log_has_three_scans_400_m_apart() -> None:
    lines = three_far_scans_log().decode().splitlines()
    scans = [line.split() for line in lines if line.startswith("FLASER")]
    assert [(float(s[182]), float(s[183])) for s in scans] == [(0.0, 0.0), (400.0, 0.0), (400.0, 400.0)]
