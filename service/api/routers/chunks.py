"""/v1/sessions/{id}/chunks: streamed sensor messages, idempotent per sequence number, and the
stream's end (/finish), which a live job waits for."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from api_schemas.chunks import ChunkCreate, ChunkPublic, StreamFinish, StreamState
from api_schemas.error_body import ErrorResponse
from service.api.convert import utc
from service.api.deps import DataDep, SessionDep, SettingsDep, StoreDep
from service.storage.chunks import check_calibration, finish_stream, store_chunk, stream_state_in_store
from service.storage.disk_space import ensure_free_space

router = APIRouter(prefix="/v1/sessions/{session_id}/chunks", tags=["chunks"],
                   responses={401: {"model": ErrorResponse}, 404: {"model": ErrorResponse},
                              413: {"model": ErrorResponse}, 422: {"model": ErrorResponse}})


@router.post("", response_model=ChunkPublic, status_code=201,
             responses={200: {"model": ChunkPublic, "description": "A retry of a chunk already received."},
                        409: {"model": ErrorResponse, "description": "Same seq, different content; or a seq "
                              "beyond the end of a finished stream."}})
def post_chunk(body: ChunkCreate, session: SessionDep, store: StoreDep, data: DataDep, settings: SettingsDep,
               request: Request, response: Response) -> ChunkPublic:
    """Append chunk ``seq``. Resending the same chunk is harmless (200, ``duplicate: true``);
    the same seq with other content is 409, and so is a seq beyond the end of a finished stream.
    Chunks may arrive out of order: the answer lists the gaps. A scan whose beam count differs
    from the session's LiDAR calibration is 422. A job maps the contiguous chunks
    0..k present when it starts; a live job maps them as they arrive, waiting at a gap."""
    declared = request.headers.get("content-length", "")
    ensure_free_space(data, settings.min_free_bytes, int(declared) if declared.isdigit() else 0)
    check_calibration(body, session.calibration)
    row, duplicate = store_chunk(store, data, session.id, body)
    if duplicate:
        response.status_code = 200
    return ChunkPublic(session_id=session.id, seq=row.seq, sha256=row.sha256, messages=row.messages,
                       t_first_s=row.t_first_s, t_last_s=row.t_last_s, duplicate=duplicate,
                       created_at=utc(row.created_at), stream=stream_state_in_store(store, session.id))


@router.get("", response_model=StreamState)
def get_stream(session: SessionDep, store: StoreDep) -> StreamState:
    """The stream's state: chunks received, the contiguous prefix, the gaps."""
    return stream_state_in_store(store, session.id)


@router.post("/finish", response_model=StreamState,
             responses={409: {"model": ErrorResponse, "description": "Finished already at another seq, or a "
                              "chunk beyond last_seq was received; or no chunks and no last_seq."}})
def finish(session: SessionDep, store: StoreDep, body: StreamFinish | None = None) -> StreamState:
    """Declare the stream's end: no chunk after ``last_seq`` (default: the highest received) will
    come. A live job maps up to it (waiting for any gap below it) and then finishes with its
    products. Repeating the call is harmless; later chunks beyond the end are refused (409)."""
    return finish_stream(store, session.id, body or StreamFinish())
