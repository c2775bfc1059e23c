"""Which requests need an API key: every path but the configured open ones (``open_paths``, by
default only /healthz), checked before any route runs, pages and the OpenAPI documents included.

A key comes as ``X-API-Key`` or ``Authorization: Bearer KEY``; for the pages outside the API (the viewer,
/docs, /openapi.json, /redoc) also as ``Authorization: Basic`` with the key as the password: those answer
401 with a Basic challenge, so a browser asks for it with its login prompt. (The API's own routes take no
Basic credentials: the viewer sends its key as ``X-API-Key``.)"""

from __future__ import annotations

import base64
import binascii
import hmac

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Receive, Scope, Send

from service.api.error_handlers import error_response

API_PREFIXES = ("/v1/", "/readyz")  # machine routes: a Bearer challenge (no browser prompt)


def offered_key(headers: Headers, basic: bool = False) -> str | None:
    """The key a request offers (None: none offered): ``X-API-Key``, a Bearer token, or with ``basic``
    the password of Basic credentials."""
    key = headers.get("x-api-key")
    if key:
        return key
    scheme, _, credentials = headers.get("authorization", "").partition(" ")
    if scheme.lower() == "bearer" and credentials.strip():
        return credentials.strip()
    if basic and scheme.lower() == "basic" and credentials.strip():
        try:
            decoded = base64.b64decode(credentials.strip(), validate=True).decode("utf-8")
        except (binascii.Error, UnicodeDecodeError):
            return None
        return decoded.partition(":")[2] or None
    return None


def is_known_key(offered: str, keys: list[str]) -> bool:
    """Whether ``offered`` is one of ``keys`` (constant-time comparison)."""
    return any(hmac.compare_digest(offered.encode(), key.encode()) for key in keys)


def is_open(path: str, open_paths: list[str]) -> bool:
    """Whether ``path`` is one of ``open_paths`` or below one."""
    return any(path == p or path.startswith(p.rstrip("/") + "/") for p in open_paths)


class KeyGateMiddleware:
    """401 for a request to a path that is not open when it offers no known key (keys configured)."""

    def __init__(self, app: ASGIApp, keys: list[str], open_paths: list[str]):
        self.app = app
        self.keys = keys
        self.open_paths = open_paths

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not self.keys or is_open(scope["path"], self.open_paths):
            await self.app(scope, receive, send)
            return
        api = scope["path"].startswith(API_PREFIXES)
        offered = offered_key(Headers(scope=scope), basic=not api)
        if offered is not None and is_known_key(offered, self.keys):
            await self.app(scope, receive, send)
            return
        challenge = "Bearer" if api else 'Basic realm="lidarmap", charset="UTF-8"'
        message = ("an API key is required (header X-API-Key or Authorization: Bearer)" if offered is None
                   else "unknown API key")
        await error_response(401, "unauthorized", message, headers={"WWW-Authenticate": challenge})(
            scope, receive, send)
