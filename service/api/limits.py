"""Request body limits, enforced while the body arrives (before any parsing): its size, and how
long the client may stall in the middle of it."""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.error_handlers import error_response


class _TooLarge(HTTPException):
    """Raised from ``receive`` while a body streams in; an HTTPException so that a route that reads
    the body itself (FastAPI parsing JSON) answers 413 through the handlers, not 'cannot parse' 400."""

    def __init__(self, limit: int):
        super().__init__(413, f"request body larger than the limit of {limit} bytes")


class _Stalled(HTTPException):
    def __init__(self, timeout_s: float):
        super().__init__(408, f"the request body stalled: no data for {timeout_s:g} s")


class BodyLimitMiddleware:
    """413 when a body exceeds ``limit_for(path)`` bytes: by Content-Length at once, otherwise
    counted as it streams in; 408 when the client sends no body data for ``stall_timeout_s``."""

    def __init__(self, app: ASGIApp, limit_for: Callable[[str], int], stall_timeout_s: float = 60.0):
        self.app = app
        self.limit_for = limit_for
        self.stall_timeout_s = stall_timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.limit_for(scope["path"])
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            await self._reject(limit, scope, receive, send)
            return
        seen = 0
        started = False
        body_done = False

        async def limited_receive() -> Message:
            nonlocal seen, body_done
            if body_done:  # after the body: waiting for a disconnect is not a stall
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), self.stall_timeout_s)
            except TimeoutError:
                raise _Stalled(self.stall_timeout_s) from None
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise _TooLarge(limit)
                body_done = not message.get("more_body", False)
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except _TooLarge:
            if started:
                raise
            await self._reject(limit, scope, receive, send)
        except _Stalled as exc:
            if started:
                raise
            await error_response(408, "request_timeout", exc.detail)(scope, receive, send)

    @staticmethod
    async def _reject(limit: int, scope: Scope, receive: Receive, send: Send) -> None:
        response = error_response(413, "payload_too_large", f"request body larger than the limit of {limit} bytes",
                                  {"limit_bytes": limit})
        await response(scope, receive, send)
