"""The job store's streamed chunks: each chunk of a session's stream recorded once (by seq and hash),
the stream's declared end, and the stream's state computed in SQL."""

from __future__ import annotations

import time
from dataclasses import dataclass

from service.storage.database import StoreBase, _Transaction
from service.storage.rows import ChunkRow, StreamFigures
from service.storage.session_records import _lock_session


@dataclass(frozen=True)
class ChunkOutcome:
    row: ChunkRow | None
    duplicate: bool
    conflict: bool
    beyond_end: int | None = None  # the stream was finished at this seq, below the chunk's: nothing stored


@dataclass(frozen=True)
class FinishOutcome:
    last_seq: int | None  # the stream's end now (None: nothing to finish, no chunk and no last_seq)
    conflict: str | None = None  # why the end could not be set (nothing was changed)


class ChunkRecords(StoreBase):
    """Streamed chunks (table ``chunks``) and the streams' ends (table ``stream_ends``); every method
    is one transaction."""

    def put_chunk(self, session_id: str, seq: int, sha256: str, messages: int,
                  t_first_s: float, t_last_s: float) -> ChunkOutcome:
        """Record chunk ``seq`` once: a retry with the same hash is a duplicate, another hash a conflict;
        a new chunk beyond the end of a finished stream is refused (``beyond_end``)."""
        row = {"session_id": session_id, "seq": seq, "sha256": sha256, "messages": messages,
               "t_first_s": t_first_s, "t_last_s": t_last_s, "created_at": time.time()}
        with self._tx() as tx:
            _lock_session(tx, session_id)
            end = _stream_end(tx, session_id)
            if end is not None and seq > end:
                return ChunkOutcome(None, duplicate=False, conflict=False, beyond_end=end)
            inserted = tx.execute(f"INSERT INTO chunks ({', '.join(row)}) VALUES ({', '.join('?' * len(row))}) "
                                  "ON CONFLICT (session_id, seq) DO NOTHING", tuple(row.values())).rowcount
            if inserted == 1:
                return ChunkOutcome(ChunkRow.from_db(row), duplicate=False, conflict=False)
            old = tx.execute("SELECT * FROM chunks WHERE session_id = ? AND seq = ?", (session_id, seq)).fetchone()
        return ChunkOutcome(ChunkRow.from_db(old), duplicate=old["sha256"] == sha256, conflict=old["sha256"] != sha256)

    def finish_stream(self, session_id: str, last_seq: int | None) -> FinishOutcome:
        """Declare the stream's last seq (default: the highest received). Idempotent for the same end;
        refused (``conflict``) for another end than the one set, or below a chunk already received."""
        with self._tx() as tx:
            _lock_session(tx, session_id)
            highest = tx.execute("SELECT max(seq) AS highest FROM chunks WHERE session_id = ?",
                                 (session_id,)).fetchone()["highest"]
            end = _stream_end(tx, session_id)
            wanted = last_seq if last_seq is not None else (end if end is not None else highest)
            if wanted is None:
                return FinishOutcome(None, "the stream has no chunks: send some, or give 'last_seq'")
            wanted = int(wanted)
            if end is not None:
                if end != wanted:
                    return FinishOutcome(end, f"the stream was already finished at seq {end}")
                return FinishOutcome(end)
            if highest is not None and int(highest) > wanted:
                return FinishOutcome(None, f"chunk {int(highest)} was already received, beyond last_seq {wanted}")
            tx.execute("INSERT INTO stream_ends (session_id, last_seq, finished_at) VALUES (?, ?, ?)",
                       (session_id, wanted, time.time()))
        return FinishOutcome(wanted)

    def stream_end(self, session_id: str) -> int | None:
        """The finished stream's last seq; None while the stream is open."""
        with self._tx() as tx:
            return _stream_end(tx, session_id)

    def delete_chunk(self, session_id: str, seq: int) -> None:
        """Forget chunk ``seq`` (its file could not be written)."""
        with self._tx() as conn:
            conn.execute("DELETE FROM chunks WHERE session_id = ? AND seq = ?", (session_id, seq))

    def chunk_rows_near(self, session_id: str, seq: int) -> list[ChunkRow]:
        """Chunks seq-1, seq and seq+1 (what a new chunk is checked against), without reading the rest."""
        with self._tx() as conn:
            rows = conn.execute("SELECT * FROM chunks WHERE session_id = ? AND seq BETWEEN ? AND ? ORDER BY seq",
                                (session_id, seq - 1, seq + 1)).fetchall()
        return [ChunkRow.from_db(r) for r in rows]

    def stream_figures(self, session_id: str, max_after: int = 5000) -> StreamFigures:
        """The stream's state computed in SQL (cheap for long streams): chunks received, the end of
        the contiguous run from seq 0 (-1: none), the messages in it, the highest seq, the seqs
        received beyond the run (at most ``max_after``, ascending) and the stream's declared last
        seq (None while open)."""
        with self._tx() as conn:
            totals = conn.execute("SELECT count(*) AS received, max(seq) AS highest FROM chunks "
                                  "WHERE session_id = ?", (session_id,)).fetchone()
            received, highest = totals["received"], totals["highest"]
            k = conn.execute(
                "SELECT CASE WHEN EXISTS (SELECT 1 FROM chunks WHERE session_id = ? AND seq = 0) THEN "
                "(SELECT min(c.seq) FROM chunks c WHERE c.session_id = ? AND NOT EXISTS "
                "(SELECT 1 FROM chunks d WHERE d.session_id = ? AND d.seq = c.seq + 1)) ELSE -1 END AS k",
                (session_id, session_id, session_id)).fetchone()["k"]
            messages = conn.execute("SELECT coalesce(sum(messages), 0) AS n FROM chunks WHERE session_id = ? "
                                    "AND seq <= ?", (session_id, k)).fetchone()["n"]
            after = [r["seq"] for r in conn.execute("SELECT seq FROM chunks WHERE session_id = ? AND seq > ? "
                                                    "ORDER BY seq LIMIT ?", (session_id, k, max_after))]
            end = _stream_end(conn, session_id)
        return StreamFigures(received=int(received), contiguous_through=int(k), messages=int(messages),
                             highest=-1 if highest is None else int(highest), after=[int(s) for s in after],
                             last_seq=end)

    def chunk_rows(self, session_id: str) -> list[ChunkRow]:
        """All chunks of a session in seq order."""
        with self._tx() as tx:
            rows = tx.execute("SELECT * FROM chunks WHERE session_id = ? ORDER BY seq", (session_id,)).fetchall()
        return [ChunkRow.from_db(r) for r in rows]


def _stream_end(tx: _Transaction, session_id: str) -> int | None:
    row = tx.execute("SELECT last_seq FROM stream_ends WHERE session_id = ?", (session_id,)).fetchone()
    return None if row is None else int(row["last_seq"])
