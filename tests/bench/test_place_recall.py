"""The place index's retrieval bench (:mod:`bench.place_recall`) on aces-rough, and the Karto table's
format (:mod:`bench.peers`; Karto itself is built from ../shared/peers, not in the suite)."""

from __future__ import annotations

from bench import peers, place_recall


def test_retrieval_at_the_true_revisits_of_aces_rough(dataset) -> None:
    dataset("benchmark/aces-rough.gt.txt")
    result = place_recall.measure("aces-rough")
    # measured 2026-11-29: 112 queries, 13 true revisits, recall@1 0.85, recall@5 1.0, precision@1 0.11
    assert result.queries > 100 and result.revisits >= 10
    assert result.retrieved_at_k >= result.retrieved_at_1 and result.retrieved_at_k / result.revisits >= 0.9
    row = result.row(5)
    assert row.startswith("| aces-rough | ") and row.count("|") == 8


def test_retrieval_at_the_true_revisits_of_intel(dataset) -> None:
    dataset("benchmark/intel.gt.txt")
    result = place_recall.measure("intel")
    # measured 2026-11-29: 130 true revisits, recall@5 0.93 (0.83 when every bin of the sectors a query saw
    # counted, and at a 12 m radius), recall@1 0.88
    assert result.revisits >= 100
    assert result.retrieved_at_k / result.revisits >= 0.9 and result.retrieved_at_1 / result.revisits >= 0.8


def test_the_karto_table_states_medians_and_their_ratio(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("LIDARMAP_KARTO", str(tmp_path / "missing"))
    assert peers.karto_binary() is None
    assert peers.main(["aces-rough"]) == 2  # not built: says how to build it
    rows = [peers.SideBySide("aces-rough", [4.0, 5.0, 9.0], [2.0, 1.0, 2.5])]
    text = peers.table(rows, 3)
    assert "| aces-rough | 5.00 | 2.00 | 2.50 |" in text and "median of 3 interleaved rounds" in text
