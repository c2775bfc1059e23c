"""The service's errors mapped onto JSON error answers.

Every non-2xx answer has the body ``{"error": {"code", "message", "detail"}}``. Engine errors keep
their meaning: an unrecognised log is 415, a corrupt one 422 with the loader's message and location.
Unexpected exceptions become a 500 with no internals in the body (they are logged).
"""

from __future__ import annotations

import logging
import sqlite3
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.http_errors import (
    InvalidInput,
    NotFound,
    ServiceError,
    UnsupportedFormat,
    is_disk_full,
    shorten_tokens,
)
from slam_engine.errors import ConfigError, LogFormatError, SlamEngineError, TileOutOfRangeError, UnknownFormatError

logger = logging.getLogger("lidarmap.service")


def error_response(status_code: int, code: str, message: str, detail: Any = None,
                   headers: dict[str, str] | None = None) -> JSONResponse:
    """The one error body (long tokens in the message cut, see :func:`shorten_tokens`)."""
    body = {"error": {"code": code, "message": shorten_tokens(message), "detail": jsonable_encoder(detail)}}
    return JSONResponse(body, status_code=status_code, headers=headers)


def engine_error_to_service(exc: SlamEngineError) -> ServiceError:
    """The HTTP meaning of an engine error."""
    if isinstance(exc, TileOutOfRangeError):
        err: ServiceError = NotFound(str(exc))
        err.code = "tile_out_of_range"
        return err
    if isinstance(exc, UnknownFormatError):
        return UnsupportedFormat(exc.message, {"path": None, "location": exc.location})
    if isinstance(exc, LogFormatError):
        # exc.path is a server-side path: report only the location inside the log.
        err = InvalidInput(exc.message, {"location": exc.location})
        err.code = "log_format"
        return err
    if isinstance(exc, ConfigError):
        err = InvalidInput(str(exc))
        err.code = "config"
        return err
    return InvalidInput(str(exc))


def install_error_handlers(app: FastAPI) -> None:
    """Route every exception to the JSON error body."""

    @app.exception_handler(ServiceError)
    async def _service(_: Request, exc: ServiceError) -> JSONResponse:
        return error_response(exc.status_code, exc.code, exc.message, exc.detail, exc.headers)

    @app.exception_handler(SlamEngineError)
    async def _engine(_: Request, exc: SlamEngineError) -> JSONResponse:
        err = engine_error_to_service(exc)
        return error_response(err.status_code, err.code, err.message, err.detail)

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError) -> JSONResponse:
        fields = [{"loc": list(e.get("loc", ())), "msg": e.get("msg"), "type": e.get("type")}
                  for e in exc.errors()]
        first = fields[0] if fields else {"loc": [], "msg": "invalid request"}
        where = ".".join(str(p) for p in first["loc"])
        return error_response(422, "validation_error", f"{where}: {first['msg']}", fields)

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        codes = {400: "bad_request", 404: "not_found", 405: "method_not_allowed", 401: "unauthorized",
                 408: "request_timeout", 413: "payload_too_large"}
        return error_response(exc.status_code, codes.get(exc.status_code, "http_error"), str(exc.detail),
                              headers=getattr(exc, "headers", None))

    @app.exception_handler(OSError)
    @app.exception_handler(sqlite3.Error)
    async def _disk_full(request: Request, exc: Exception) -> JSONResponse:
        if not disk_full(request, exc):
            raise exc  # to the 500 handler below
        return _insufficient_storage(request, exc)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        if disk_full(request, exc):  # e.g. PostgreSQL's disk_full
            return _insufficient_storage(request, exc)
        logger.exception("unhandled error on %s %s", request.method, request.url.path)
        return error_response(500, "internal_error", "internal error (logged on the server)")


def disk_full(request: Request, exc: BaseException) -> bool:
    """Whether ``exc`` means a full disk (see :func:`is_disk_full`; the data folder's free space decides
    an SQLite I/O error)."""
    data = getattr(request.app.state, "data", None)
    try:
        free = data.free_bytes() if data is not None else None
    except OSError:
        free = None
    return is_disk_full(exc, free)


def _insufficient_storage(request: Request, exc: BaseException) -> JSONResponse:
    logger.error("disk full on %s %s: %s", request.method, request.url.path, exc)
    return error_response(507, "insufficient_storage", "the server's disk is full: nothing was stored; retry later")
