"""Streamed chunks: canonical form, hashing, ordering checks, storage, the stream's state and its end."""

from __future__ import annotations

import hashlib
import json
from typing import Any

from api_schemas.chunks import ChunkCreate, StreamFinish, StreamState
from service.http_errors import Conflict, InvalidInput
from service.storage.data_dir import DataDir, write_atomic
from service.storage.disk_space import disk_full_error
from service.storage.rows import ChunkRow
from service.storage.store import JobStore

MAX_MISSING_LISTED = 100


def canonical_messages(chunk: ChunkCreate) -> bytes:
    """The chunk's messages as canonical JSON (sorted keys, no spaces): equal content, equal bytes."""
    messages = [m.model_dump(mode="json") for m in chunk.messages]
    return json.dumps(messages, sort_keys=True, separators=(",", ":")).encode()


def check_time_order(chunk: ChunkCreate) -> None:
    """Messages within a chunk must not go back in time."""
    previous = None
    for i, message in enumerate(chunk.messages):
        if previous is not None and message.t_s < previous:
            raise InvalidInput(f"chunk {chunk.seq}: message {i} at t={message.t_s} s is earlier than message "
                               f"{i - 1} at t={previous} s; send messages in time order",
                               {"seq": chunk.seq, "message_index": i})
        previous = message.t_s


def check_calibration(chunk: ChunkCreate, calibration: dict[str, Any] | None) -> None:
    """Scans must have the beam count of the session's LiDAR (a wrong one would break every later job)."""
    lidar = (calibration or {}).get("lidar")
    if not lidar:
        return
    beams = lidar["num_beams"]
    for i, message in enumerate(chunk.messages):
        if message.type == "scan" and len(message.ranges_m) != beams:
            raise InvalidInput(f"chunk {chunk.seq}: scan message {i} has {len(message.ranges_m)} ranges; the "
                               f"session's LiDAR has {beams} beams", {"seq": chunk.seq, "message_index": i,
                                                                     "num_beams": beams})


def check_neighbours(chunk: ChunkCreate, rows: list[ChunkRow]) -> None:
    """A chunk must fit in time between its neighbours by seq (if they arrived)."""
    t_first, t_last = chunk.messages[0].t_s, chunk.messages[-1].t_s
    by_seq = {r.seq: r for r in rows}
    before, after = by_seq.get(chunk.seq - 1), by_seq.get(chunk.seq + 1)
    if before is not None and t_first < before.t_last_s:
        raise InvalidInput(f"chunk {chunk.seq} starts at t={t_first} s, before chunk {chunk.seq - 1} ends "
                           f"(t={before.t_last_s} s): chunks must follow each other in time",
                           {"seq": chunk.seq, "previous_t_last_s": before.t_last_s})
    if after is not None and t_last > after.t_first_s:
        raise InvalidInput(f"chunk {chunk.seq} ends at t={t_last} s, after chunk {chunk.seq + 1} starts "
                           f"(t={after.t_first_s} s): chunks must follow each other in time",
                           {"seq": chunk.seq, "next_t_first_s": after.t_first_s})


def stream_state(rows: list[ChunkRow]) -> StreamState:
    """What arrived, the contiguous prefix 0..k a job would map, and the gaps."""
    seqs = {r.seq for r in rows}
    k = -1
    while k + 1 in seqs:
        k += 1
    highest = max(seqs, default=-1)
    missing = [s for s in range(k + 1, highest) if s not in seqs][:MAX_MISSING_LISTED]
    messages = sum(r.messages for r in rows if r.seq <= k)
    return StreamState(received=len(seqs), contiguous_through=k, next_expected_seq=k + 1,
                       missing_seqs=missing, messages=messages)


def stream_state_in_store(store: JobStore, session_id: str) -> StreamState:
    """:func:`stream_state` of the session's chunks, computed by the store without reading every row."""
    figures = store.stream_figures(session_id)
    k, after = figures.contiguous_through, figures.after
    present, missing = set(after), []
    last = figures.highest if len(after) < 5000 else (after[-1] if after else k)
    for seq in range(k + 1, last):
        if seq not in present:
            missing.append(seq)
            if len(missing) == MAX_MISSING_LISTED:
                break
    end = figures.last_seq
    return StreamState(received=figures.received, contiguous_through=k, next_expected_seq=k + 1,
                       missing_seqs=missing, messages=figures.messages, finished=end is not None, last_seq=end)


def finish_stream(store: JobStore, session_id: str, body: StreamFinish) -> StreamState:
    """Set the stream's end (idempotent); 409 when it contradicts the end already set or a chunk received."""
    outcome = store.finish_stream(session_id, body.last_seq)
    if outcome.conflict is not None:
        raise Conflict(f"cannot finish the stream: {outcome.conflict}",
                       {"last_seq": outcome.last_seq, "requested_last_seq": body.last_seq})
    return stream_state_in_store(store, session_id)


def store_chunk(store: JobStore, data: DataDir, session_id: str, chunk: ChunkCreate) -> tuple[ChunkRow, bool]:
    """Record and save a chunk once. Returns (row, duplicate); 409 when ``seq`` exists with other content."""
    check_time_order(chunk)
    body = canonical_messages(chunk)
    digest = hashlib.sha256(body).hexdigest()
    rows = store.chunk_rows_near(session_id, chunk.seq)
    known = next((r for r in rows if r.seq == chunk.seq), None)
    if known is None:
        end = store.stream_end(session_id)
        if end is not None and chunk.seq > end:  # the clearer answer first (put_chunk checks it atomically)
            raise _beyond_end(chunk.seq, end)
        check_neighbours(chunk, rows)
    outcome = store.put_chunk(session_id, chunk.seq, digest, len(chunk.messages),
                              chunk.messages[0].t_s, chunk.messages[-1].t_s)
    if outcome.beyond_end is not None:
        raise _beyond_end(chunk.seq, outcome.beyond_end)
    assert outcome.row is not None  # stored now, or the one stored before
    if outcome.conflict:
        raise Conflict(f"chunk {chunk.seq} was already received with different content",
                       {"seq": chunk.seq, "stored_sha256": outcome.row.sha256, "sent_sha256": digest})
    path = data.chunk_file(session_id, chunk.seq)
    if not outcome.duplicate or not path.exists():  # a retry after a crash between row and file heals it
        try:
            write_atomic(path, body)
        except OSError as exc:
            if not outcome.duplicate:  # no row without its file: the client's retry will store both
                store.delete_chunk(session_id, chunk.seq)
            raise disk_full_error(exc, f"chunk {chunk.seq}") or exc from None
    return outcome.row, outcome.duplicate


def _beyond_end(seq: int, last_seq: int) -> Conflict:
    return Conflict(f"the stream was finished at seq {last_seq}: chunk {seq} is beyond its end (start a new "
                    "session for more data)", {"seq": seq, "last_seq": last_seq})


def read_chunk_messages(data: DataDir, session_id: str, seq: int) -> list[dict[str, Any]]:
    """The stored canonical messages of chunk ``seq``."""
    return json.loads(data.chunk_file(session_id, seq).read_bytes())
