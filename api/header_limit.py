"""A cap on the size of a request's head (request line and headers together): past
``NEPF_MAX_HEADER_BYTES`` (64 KiB) the answer is **431** ``headers_too_large``.

Two layers, because uvicorn with httptools (``uvicorn[standard]``, what ``nepf serve`` runs)
has no header limit at all: a 16 MB ``Authorization`` header was read in full and answered 401.

* :func:`header_limited_protocol`: the HTTP protocol ``nepf serve`` hands to uvicorn, uvicorn's
  own httptools protocol counting the bytes a request's head takes while it arrives. Past the
  cap it answers 431 and closes the connection at once, so a client cannot make the server read
  (and buffer) an endless head. Without httptools, uvicorn's h11 protocol is bounded with its
  own ``h11_max_incomplete_event_size`` instead (its answer is then a 400).
* :class:`HeaderLimit`: an ASGI middleware with the same cap, for every other way of serving the
  app (``uvicorn api.main:app``, another ASGI server, the test client). It sees the head only
  once the server has parsed it, so it bounds what reaches the app, not what the server reads.
"""

from __future__ import annotations

import json
import logging
from typing import Optional

from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Receive, Scope, Send

from .errors import ApiError

log = logging.getLogger("nepf.api")

#: what one header costs on the wire besides its name and value: ``": "`` and ``"\r\n"``
HEADER_OVERHEAD = 4


def headers_too_large(limit: int) -> ApiError:
    return ApiError(431, "headers_too_large",
                    f"the request line and headers exceed {limit} bytes (NEPF_MAX_HEADER_BYTES)")


def head_bytes(scope: Scope) -> int:
    """Bytes of a parsed request head: target (path and query) and every header."""
    target = len(scope.get("raw_path") or scope.get("path", "").encode()) + len(scope.get("query_string") or b"")
    return target + sum(len(k) + len(v) + HEADER_OVERHEAD for k, v in scope.get("headers") or [])


class HeaderLimit:
    """Pure ASGI middleware: a 431 for an HTTP request whose head is over ``limit`` bytes."""

    def __init__(self, app: ASGIApp, limit: int) -> None:
        self.app, self.limit = app, limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and self.limit > 0 and head_bytes(scope) > self.limit:
            err = headers_too_large(self.limit)
            await JSONResponse(err.body(), status_code=431, headers={"Connection": "close"})(scope, receive, send)
            return
        await self.app(scope, receive, send)


def header_limited_protocol(limit: int) -> Optional[type]:
    """uvicorn's httptools protocol with the head capped at ``limit`` bytes (module docstring),
    or None when httptools is not installed (then bound h11 instead, see :func:`uvicorn_options`)."""
    try:
        import httptools
        from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol
    except ImportError:
        return None

    class HeaderLimitedHttpToolsProtocol(HttpToolsProtocol):
        """Counts the bytes of each request's head twice: every byte received while a head is
        incomplete (so an endless head is cut after ``limit`` bytes, before httptools has
        buffered more), and exactly, from the target and the headers, once it is complete."""

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self._in_head, self._received, self._exact, self._refused = True, 0, 0, False

        def on_message_begin(self) -> None:
            super().on_message_begin()
            self._exact = 0

        def on_url(self, url: bytes) -> None:
            self._exact += len(url)
            super().on_url(url)

        def on_header(self, name: bytes, value: bytes) -> None:
            self._exact += len(name) + len(value) + HEADER_OVERHEAD
            if self._exact <= limit:      # past the cap, keep nothing: the request is refused anyway
                super().on_header(name, value)

        def on_headers_complete(self) -> None:
            self._in_head = False
            if self._exact > limit:
                self._refused = True
                raise ValueError("request head too large")   # stops the parser; see send_400_response
            super().on_headers_complete()

        def on_message_complete(self) -> None:
            super().on_message_complete()
            self._in_head, self._received = True, 0

        def data_received(self, data: bytes) -> None:
            if self._in_head:
                self._received += len(data)
            super().data_received(data)
            if self._in_head and self._received > limit and not self._refused:
                self._refused = True
                self._send_431()

        def send_400_response(self, msg: str) -> None:
            # uvicorn answers any parser error (ours above included) with a 400
            if self._refused:
                self._send_431()
            else:
                super().send_400_response(msg)

        def _send_431(self) -> None:
            log.warning("refused a request whose head exceeds %d bytes (431)", limit)
            body = json.dumps(headers_too_large(limit).body()).encode()
            head = [b"HTTP/1.1 431 Request Header Fields Too Large\r\n"]
            for name, value in self.server_state.default_headers:
                head += [name, b": ", value, b"\r\n"]
            head += [b"content-type: application/json\r\n", b"content-length: %d\r\n" % len(body),
                     b"connection: close\r\n\r\n"]
            if not self.transport.is_closing():
                self.transport.write(b"".join(head) + body)
                self.transport.close()

    assert issubclass(httptools.HttpParserCallbackError, httptools.HttpParserError)   # what uvicorn catches
    return HeaderLimitedHttpToolsProtocol


def uvicorn_options(limit: int) -> dict:
    """Keyword arguments for ``uvicorn.run`` that bound the request head (module docstring)."""
    if limit <= 0:
        return {}
    protocol = header_limited_protocol(limit)
    return {"http": protocol} if protocol is not None else {"http": "h11", "h11_max_incomplete_event_size": limit}
