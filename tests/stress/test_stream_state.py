"""The stream state computed in SQL (what every chunk POST answers, cheap for long streams) equals
the one computed from every chunk row, for any set of received seqs."""

from __future__ import annotations

import tempfile
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.storage.chunks import stream_state, stream_state_in_store
from service.storage.store import JobStore


@settings(max_examples=60, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(seqs=st.sets(st.integers(0, 400), max_size=300), messages=st.integers(1, 3))
def test_sql_stream_state_matches_the_row_by_row_one(seqs: set[int], messages: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        store = JobStore(Path(tmp) / "db.sqlite3")
        store.initialise()
        for seq in sorted(seqs):
            store.put_chunk("s", seq, f"h{seq}", messages + seq % 2, float(seq), float(seq) + 0.5)
        store.put_chunk("other", 0, "h", 1, 0.0, 0.0)
        assert stream_state_in_store(store, "s") == stream_state(store.chunk_rows("s"))
