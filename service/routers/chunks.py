"""/v1/sessions/{id}/chunks: streamed sensor messages, idempotent per sequence number."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response

from api_schemas.chunks import ChunkCreate, ChunkPublic, StreamState
from api_schemas.errors import ErrorResponse
from service.chunks import store_chunk, stream_state_in_store
from service.deps import DataDep, SessionRow, SettingsDep, StoreDep
from service.disk_space import ensure_free_space
from service.routers.convert import utc

router = APIRouter(prefix="/v1/sessions/{session_id}/chunks", tags=["chunks"],
                   responses={401: {"model": ErrorResponse}, 404: {"model": ErrorResponse},
                              413: {"model": ErrorResponse}, 422: {"model": ErrorResponse}})


@router.post("", response_model=ChunkPublic, status_code=201,
             responses={200: {"model": ChunkPublic, "description": "A retry of a chunk already received."},
                        409: {"model": ErrorResponse, "description": "Same seq, different content."}})
def post_chunk(body: ChunkCreate, session: SessionRow, store: StoreDep, data: DataDep, settings: SettingsDep,
               request: Request, response: Response) -> ChunkPublic:
    """Append chunk ``seq``. Resending the same chunk is harmless (200, ``duplicate: true``);
    the same seq with other content is 409. Chunks may arrive out of order: the answer lists the
    gaps, and a job maps the contiguous chunks 0..k present when it starts."""
    declared = request.headers.get("content-length", "")
    ensure_free_space(data, settings.min_free_bytes, int(declared) if declared.isdigit() else 0)
    row, duplicate = store_chunk(store, data, session["id"], body)
    if duplicate:
        response.status_code = 200
    return ChunkPublic(session_id=session["id"], seq=row["seq"], sha256=row["sha256"], messages=row["messages"],
                       t_first_s=row["t_first_s"], t_last_s=row["t_last_s"], duplicate=duplicate,
                       created_at=utc(row["created_at"]), stream=stream_state_in_store(store, session["id"]))


@router.get("", response_model=StreamState)
def get_stream(session: SessionRow, store: StoreDep) -> StreamState:
    """The stream's state: chunks received, the contiguous prefix, the gaps."""
    return stream_state_in_store(store, session["id"])
