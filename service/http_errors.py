"""The service's exception hierarchy: each error fixes its HTTP status and code
(:mod:`service.api.error_handlers` turns them into JSON answers). No web framework here: the storage,
the jobs and the worker processes raise these too."""

from __future__ import annotations

import errno
import re
import sqlite3
from typing import Any

MAX_TOKEN_CHARS = 80  # a longer word quoted in a message (a log's line, a file name) is cut to this
MAX_MESSAGE_CHARS = 2000
_LONG_TOKEN = re.compile(rf"\S{{{MAX_TOKEN_CHARS + 1},}}")


def shorten_tokens(message: str) -> str:
    """``message`` with every token longer than MAX_TOKEN_CHARS cut to its start and its length, and
    the whole cut to MAX_MESSAGE_CHARS: error answers never echo a hostile input whole."""
    short = _LONG_TOKEN.sub(lambda m: f"{m.group()[:MAX_TOKEN_CHARS]} ...({len(m.group())} characters)", message)
    if len(short) > MAX_MESSAGE_CHARS:
        short = f"{short[:MAX_MESSAGE_CHARS]} ...({len(short)} characters)"
    return short


class ServiceError(Exception):
    """Root of the errors the service raises on purpose; subclasses fix status and code."""

    status_code = 500
    code = "internal_error"

    def __init__(self, message: str, detail: Any = None, headers: dict[str, str] | None = None):
        super().__init__(message)
        self.message = message
        self.detail = detail
        self.headers = headers


class BadRequest(ServiceError):
    status_code, code = 400, "bad_request"


class NotFound(ServiceError):
    status_code, code = 404, "not_found"


class Unauthorized(ServiceError):
    status_code, code = 401, "unauthorized"


class Conflict(ServiceError):
    status_code, code = 409, "conflict"


class NotReady(ServiceError):
    """A product that does not exist (yet) for this job."""

    status_code, code = 409, "not_ready"


class PayloadTooLarge(ServiceError):
    status_code, code = 413, "payload_too_large"


class UnsupportedFormat(ServiceError):
    status_code, code = 415, "unsupported_format"


class InvalidInput(ServiceError):
    status_code, code = 422, "invalid_input"


class InsufficientStorage(ServiceError):
    """The disk is full (or below the configured reserve): nothing was stored."""

    status_code, code = 507, "insufficient_storage"


class Unavailable(ServiceError):
    status_code, code = 503, "unavailable"


LOW_SPACE_BYTES = 16 * 1024**2  # below this much free space an SQLite "disk I/O error" means a full disk
SQLITE_IOERR, SQLITE_FULL = 10, 13  # primary result codes (an extended code's low byte)
POSTGRES_DISK_FULL = "53100"  # SQLSTATE disk_full


def is_disk_full(exc: BaseException, free_bytes: int | None = None) -> bool:
    """Whether ``exc`` says the disk is full: an OSError ENOSPC/EDQUOT, SQLite's 'database or disk is
    full', PostgreSQL's disk_full; or SQLite's 'disk I/O error' while the data folder has less than
    LOW_SPACE_BYTES free (``free_bytes``; what SQLite answers when its write-ahead log cannot grow)."""
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    if getattr(exc, "sqlstate", None) == POSTGRES_DISK_FULL:
        return True
    if not isinstance(exc, sqlite3.Error):
        return False
    code = (getattr(exc, "sqlite_errorcode", None) or 0) & 0xFF
    if code == SQLITE_FULL or "full" in str(exc):
        return True
    io_error = code == SQLITE_IOERR or "disk I/O error" in str(exc)
    return io_error and free_bytes is not None and free_bytes < LOW_SPACE_BYTES
