"""The place index's retrieval bench (:mod:`bench.place_recall`) on aces-rough, and the Karto table's
format (:mod:`bench.peers`; Karto itself is built from ../shared/peers, not in the suite)."""

from __future__ import annotations

import json
import sys

import pytest

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
    rows = [peers.SideBySide("aces-rough", [4.0, 5.0, 9.0], [2.0, 1.0, 2.5], [310.0, 320.0, 300.0], [22.0, 29.0, 25.0],
                             peers.Scored(0.0378, 878, 878), peers.Scored(0.1965, 870, 878))]
    text = peers.table(rows, 3)
    assert "| aces-rough | 5.00 | 2.00 | 2.50 | 310 / 25 | 0.038 / 0.197 (870/878) |" in text
    assert "median of 3 interleaved rounds" in text
    assert peers.SideBySide("intel", [1.0], [2.0]).row() == "| intel | 1.00 | 2.00 | 0.50 | – | – |"


def test_the_peers_scores_are_what_each_wrote(tmp_path) -> None:
    """Karto's poses scored against the relations (a relation at a scan it skipped is not matched), and
    lidarmap's from its run.json."""
    relations = tmp_path / "log.relations"
    relations.write_text("0.0 1.0 1.0 0.0 0 0 0 0.0\n1.0 2.0 1.0 0.0 0 0 0 0.0\n2.0 3.0 1.0 0.0 0 0 0 0.0\n")
    poses = tmp_path / "karto.txt"
    poses.write_text("0.0 0.0 0.0 0.0\n1.0 1.1 0.0 0.0\n2.0 2.0 0.0 0.0\n")  # the scan at 3 s skipped
    scored = peers.karto_error(poses, relations)
    assert scored is not None and (scored.matched, scored.relations) == (2, 3)
    assert scored.trans_mean_m == pytest.approx(0.1)  # 0.1 m off on both matched relations
    assert peers.karto_error(poses, tmp_path / "none.relations") is None
    (tmp_path / "run.json").write_text(json.dumps({"accuracy": {"relations": {"all": {
        "n_relations": 878, "n_failed": 0, "trans_mean_m": 0.0378}}}}))
    assert peers.lidarmap_error(tmp_path) == peers.Scored(0.0378, 878, 878)
    (tmp_path / "run.json").write_text(json.dumps({"accuracy": None}))
    assert peers.lidarmap_error(tmp_path) is None


def test_a_whole_process_is_timed_with_its_own_peak_memory() -> None:
    """Its own peak, not this (large) process's: a forked child's high-water mark starts at its parent's."""
    allocate = "b = bytearray(120 * 2**20); b[::4096] = b'x' * len(b[::4096])"  # every page touched
    ballast = bytearray(300 * 2**20)
    ballast[::4096] = b"x" * len(ballast[::4096])  # this process now holds 300 MB more
    wall_s, peak_mb = peers._timed([sys.executable, "-c", allocate])
    assert wall_s > 0 and 120 <= peak_mb < 200
    small_s, small_mb = peers._timed([sys.executable, "-c", "pass"])
    assert small_mb < 40  # a bare Python, whatever this process holds
    del ballast
    with pytest.raises(RuntimeError, match="failed \\(3\\): no such thing"):
        peers._timed([sys.executable, "-c", "import sys; sys.stderr.write('no such thing'); sys.exit(3)"])
