"""Serving the app with uvicorn, the request head bounded: a request line and headers larger than
``max_header_bytes`` are answered 431 and the connection closed, before any of it is parsed further.

The HTTP parser uvicorn uses (httptools) accepts a header of any size and grows it piece by piece, so
one request with a 64 MB header held the event loop for seconds; the bound is counted on the bytes
received while the head is incomplete, a few hundred kB at most past the limit."""

from __future__ import annotations

import json
from typing import Any

import uvicorn
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol


class HeadLimitedProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol with a bound on the request head [bytes]; subclasses set it."""

    max_head_bytes = 64 * 1024

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._in_head = True
        self._head_bytes = 0

    def data_received(self, data: bytes) -> None:
        if not self._in_head:
            super().data_received(data)
            return
        self._head_bytes += len(data)
        super().data_received(data)  # at most one read (<= 256 kB) parsed past the limit
        if self._in_head and self._head_bytes > self.max_head_bytes and not self.transport.is_closing():
            self._send_431()

    def on_headers_complete(self) -> None:
        self._in_head = False
        super().on_headers_complete()

    def on_message_complete(self) -> None:
        super().on_message_complete()
        self._in_head, self._head_bytes = True, 0  # the next request on this connection

    def _send_431(self) -> None:
        body = json.dumps({"error": {"code": "request_header_fields_too_large",
                                     "message": f"the request line and headers are larger than the limit of "
                                                f"{self.max_head_bytes} bytes",
                                     "detail": {"limit_bytes": self.max_head_bytes}}}).encode()
        self.transport.write(b"HTTP/1.1 431 Request Header Fields Too Large\r\ncontent-type: application/json\r\n"
                             b"content-length: " + str(len(body)).encode() + b"\r\nconnection: close\r\n\r\n" + body)
        self.transport.close()


def head_limited_protocol(max_head_bytes: int) -> type[HeadLimitedProtocol]:
    """The protocol class for uvicorn's ``http`` option, bounded at ``max_head_bytes``."""
    return type("HeadLimitedProtocol", (HeadLimitedProtocol,), {"max_head_bytes": max_head_bytes})


def server_config(app: Any, host: str, port: int, max_head_bytes: int, **options: Any) -> uvicorn.Config:
    """uvicorn's configuration for ``app`` with the bounded request head."""
    return uvicorn.Config(app, host=host, port=port, http=head_limited_protocol(max_head_bytes), **options)


def serve(app: Any, host: str, port: int, max_head_bytes: int, **options: Any) -> None:
    """Run ``app`` until interrupted (what ``lidarmap serve`` does)."""
    uvicorn.Server(server_config(app, host, port, max_head_bytes, **options)).run()
