"""The job store's streamed chunks: each chunk of a session's stream recorded once (by seq and hash),
the stream's declared end, and the stream's state computed in SQL."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from sqlalchemy import Connection, case, delete, exists, func, insert, literal, select
from sqlalchemy.exc import IntegrityError

from service.storage.database import StoreBase
from service.storage.rows import ChunkRow, StreamFigures
from service.storage.session_records import _lock_session
from service.storage.tables import chunks, stream_ends


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
            try:
                with tx.begin_nested():  # a savepoint: a chunk already there leaves the transaction usable
                    tx.execute(insert(chunks).values(**row))
                return ChunkOutcome(ChunkRow.from_db(row), duplicate=False, conflict=False)
            except IntegrityError:
                pass  # (session_id, seq) is taken: a retry or a conflict
            old = tx.execute(select(chunks).where(chunks.c.session_id == session_id, chunks.c.seq == seq)
                             ).mappings().one()
        return ChunkOutcome(ChunkRow.from_db(old), duplicate=old["sha256"] == sha256, conflict=old["sha256"] != sha256)

    def finish_stream(self, session_id: str, last_seq: int | None) -> FinishOutcome:
        """Declare the stream's last seq (default: the highest received). Idempotent for the same end;
        refused (``conflict``) for another end than the one set, or below a chunk already received."""
        with self._tx() as tx:
            _lock_session(tx, session_id)
            highest = tx.execute(select(func.max(chunks.c.seq)).where(chunks.c.session_id == session_id)).scalar()
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
            tx.execute(insert(stream_ends).values(session_id=session_id, last_seq=wanted, finished_at=time.time()))
        return FinishOutcome(wanted)

    def stream_end(self, session_id: str) -> int | None:
        """The finished stream's last seq; None while the stream is open."""
        with self._tx() as tx:
            return _stream_end(tx, session_id)

    def delete_chunk(self, session_id: str, seq: int) -> None:
        """Forget chunk ``seq`` (its file could not be written)."""
        with self._tx() as tx:
            tx.execute(delete(chunks).where(chunks.c.session_id == session_id, chunks.c.seq == seq))

    def chunk_rows_near(self, session_id: str, seq: int) -> list[ChunkRow]:
        """Chunks seq-1, seq and seq+1 (what a new chunk is checked against), without reading the rest."""
        with self._tx() as tx:
            rows = tx.execute(select(chunks).where(chunks.c.session_id == session_id,
                                                   chunks.c.seq.between(seq - 1, seq + 1))
                              .order_by(chunks.c.seq)).mappings().all()
        return [ChunkRow.from_db(r) for r in rows]

    def stream_figures(self, session_id: str, max_after: int = 5000) -> StreamFigures:
        """The stream's state computed in SQL (cheap for long streams): chunks received, the end of
        the contiguous run from seq 0 (-1: none), the messages in it, the highest seq, the seqs
        received beyond the run (at most ``max_after``, ascending) and the stream's declared last
        seq (None while open)."""
        of_session = chunks.c.session_id == session_id
        with self._tx() as tx:
            received, highest = tx.execute(select(func.count(), func.max(chunks.c.seq)).where(of_session)).one()
            k = tx.execute(select(_contiguous_through(session_id))).scalar_one()
            messages = tx.execute(select(func.coalesce(func.sum(chunks.c.messages), 0))
                                  .where(of_session, chunks.c.seq <= k)).scalar_one()
            after = list(tx.execute(select(chunks.c.seq).where(of_session, chunks.c.seq > k)
                                    .order_by(chunks.c.seq).limit(max_after)).scalars())
            end = _stream_end(tx, session_id)
        return StreamFigures(received=int(received), contiguous_through=int(k), messages=int(messages),
                             highest=-1 if highest is None else int(highest), after=[int(s) for s in after],
                             last_seq=end)

    def chunk_rows(self, session_id: str) -> list[ChunkRow]:
        """All chunks of a session in seq order."""
        with self._tx() as tx:
            rows = tx.execute(select(chunks).where(chunks.c.session_id == session_id).order_by(chunks.c.seq)
                              ).mappings().all()
        return [ChunkRow.from_db(r) for r in rows]


def _stream_end(tx: Connection, session_id: str) -> int | None:
    last_seq = tx.execute(select(stream_ends.c.last_seq).where(stream_ends.c.session_id == session_id)).scalar()
    return None if last_seq is None else int(last_seq)


def _contiguous_through(session_id: str) -> Any:
    """The end of the run of seqs from 0 (-1 without chunk 0): the lowest seq whose successor is missing."""
    c, d = chunks.alias("c"), chunks.alias("d")
    has_zero = exists().where(chunks.c.session_id == session_id, chunks.c.seq == 0)
    successor = exists().where(d.c.session_id == session_id, d.c.seq == c.c.seq + 1)
    first_gap = select(func.min(c.c.seq)).where(c.c.session_id == session_id, ~successor).scalar_subquery()
    return case((has_zero, first_gap), else_=literal(-1)).label("k")
