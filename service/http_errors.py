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


def is_disk_full(exc: BaseException) -> bool:
    """An OSError ENOSPC/EDQUOT, or SQLite's 'database or disk is full'."""
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    return isinstance(exc, sqlite3.OperationalError) and "full" in str(exc)
