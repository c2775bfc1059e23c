"""The one error body every non-2xx answer carries: ``{"error": {"code", "message", "detail"}}``."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, Field


class ErrorBody(BaseModel):
    code: str = Field(description="Stable machine-readable code, e.g. 'not_found', 'log_format'.")
    message: str = Field(description="What is wrong, for a person.")
    detail: Any = Field(None, description="Where it is wrong: field paths, file, line or record.")


class ErrorResponse(BaseModel):
    error: ErrorBody
