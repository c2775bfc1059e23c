"""OPTIONS and wrong methods answered with ``Allow``: the methods of every route on the path; HEAD for
every GET.

Starlette answers a method that no route takes with 405 and the methods of only one of the routes
on the path, and OPTIONS alike; here OPTIONS is 204 and any other method the path does not take 405,
both with ``Allow`` listing them all. A HEAD on a path whose routes take GET but no HEAD is the GET
without its body (routes whose body is costly have their own HEAD). The table comes from the app's
OpenAPI document (its public list of paths and methods), built on first use."""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.error_handlers import error_response

HTTP_METHODS = {"get", "head", "post", "put", "patch", "delete", "options", "trace"}


def _path_regex(template: str) -> re.Pattern[str]:
    """'/v1/jobs/{job_id}' -> a regex matching one such path ('{name:path}' spans slashes)."""
    parts = re.split(r"(\{[^}]+\})", template)
    pattern = "".join((".+" if p.endswith(":path}") else "[^/]+") if p.startswith("{") else re.escape(p)
                      for p in parts)
    return re.compile(f"^{pattern}$")


class AllowedMethodsMiddleware:
    """Answer OPTIONS (204) and methods a documented path does not take (405) with ``Allow``."""

    def __init__(self, app: ASGIApp, openapi: Callable[[], dict[str, Any]]):
        self.app = app
        self.openapi = openapi
        self._table: list[tuple[re.Pattern[str], set[str]]] | None = None

    def allowed(self, path: str) -> set[str]:
        """The methods of every documented route whose path template matches ``path`` (empty: none)."""
        if self._table is None:
            self._table = [(_path_regex(template), {m.upper() for m in item if m in HTTP_METHODS})
                           for template, item in self.openapi().get("paths", {}).items()]
        methods: set[str] = set()
        for regex, verbs in self._table:
            if regex.match(path):
                methods |= verbs
        return methods

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        methods = self.allowed(scope["path"])
        if not methods or scope["method"] in methods:  # undocumented path, or a method it takes
            await self.app(scope, receive, send)
            return
        if scope["method"] == "HEAD" and "GET" in methods:
            await self.app({**scope, "method": "GET"}, receive, _without_body(send))
            return
        methods = methods | {"HEAD"} if "GET" in methods else methods
        allow = ", ".join(sorted(methods | {"OPTIONS"}))
        if scope["method"] == "OPTIONS":
            await send({"type": "http.response.start", "status": 204, "headers": [(b"allow", allow.encode())]})
            await send({"type": "http.response.body", "body": b""})
            return
        await error_response(405, "method_not_allowed", f"{scope['method']} is not allowed here; allowed: {allow}",
                             {"allow": sorted(methods | {"OPTIONS"})}, headers={"Allow": allow})(scope, receive, send)


def _without_body(send: Send) -> Send:
    """``send`` that passes the response's start (status, headers: its Content-Length) and no body."""

    async def head_send(message: Message) -> None:
        if message["type"] != "http.response.body":
            await send(message)
        elif not message.get("more_body", False):
            await send({"type": "http.response.body", "body": b"", "more_body": False})

    return head_send
