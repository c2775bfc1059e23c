"""Streamed sensor messages: numbered chunks, idempotent on retry."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, ConfigDict, Field

from api_schemas.drivelog import DriveLogMessage as Message

MAX_MESSAGES_PER_CHUNK = 10_000


class ChunkCreate(BaseModel):
    """One chunk of a stream: ``seq`` counts from 0 without gaps; messages in time order."""

    model_config = ConfigDict(extra="forbid")

    seq: int = Field(strict=True, ge=0, le=10_000_000, description="Sequence number, 0, 1, 2, ... per session.")
    messages: list[Message] = Field(min_length=1, max_length=MAX_MESSAGES_PER_CHUNK)


class StreamFinish(BaseModel):
    """The end of a stream: no chunk beyond ``last_seq`` will come."""

    model_config = ConfigDict(extra="forbid")

    last_seq: int | None = Field(None, strict=True,
                                 ge=0, le=10_000_000, description="The stream's last seq (default: the "
                                 "highest received). Chunks up to it that have not arrived yet are still "
                                 "accepted (a live job waits for them); chunks beyond it are refused (409).")


class StreamState(BaseModel):
    """The session's stream after this chunk: what arrived and what is missing."""

    received: int = Field(description="Distinct chunks received.")
    contiguous_through: int = Field(description="Highest seq such that 0..seq all arrived (-1: none).")
    next_expected_seq: int
    missing_seqs: list[int] = Field(description="Gaps below the highest seq received (at most 100 listed).")
    messages: int = Field(description="Messages in the contiguous chunks 0..contiguous_through.")
    finished: bool = Field(False, description="True once the client declared the stream's end "
                           "(POST /v1/sessions/{id}/chunks/finish).")
    last_seq: int | None = Field(None, description="The stream's last seq once finished; null while it is open.")


class ChunkPublic(BaseModel):
    session_id: str
    seq: int
    sha256: str = Field(description="sha256 of the canonical JSON of the chunk's messages.")
    messages: int
    t_first_s: float
    t_last_s: float
    duplicate: bool = Field(description="True when this exact chunk had already been received (a retry).")
    created_at: datetime
    stream: StreamState
