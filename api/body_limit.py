"""A cap on the whole request body of the upload route, enforced while the body is read.

The multipart parser only counts the parts it knows, and a chunked request has no
Content-Length, so neither bounds what a client may send. This ASGI middleware counts every body
byte the app pulls from ``receive()`` on a capped route and raises a 413 :class:`ApiError` (the
status ``receive_multipart`` uses for the dataset part) as soon as the count passes the cap: the
route's cleanup runs, and the server reads no further: uvicorn pauses the socket while the app
is not receiving, and a response sent before the body was read to its end (413, or 401, 415 ...)
carries ``Connection: close``, without which uvicorn would drain the rest of the body to keep
the connection alive. A Content-Length above the cap is refused before any byte is read.

For ``POST /jobs``: ``cap = NEPF_MAX_UPLOAD_MB + MAX_CONFIG_BYTES + ENVELOPE_BYTES`` (part headers
and boundaries), so a body that passes it still meets the dataset part's own, exact cap.
"""

from __future__ import annotations

from typing import Callable

from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .errors import ApiError
from jobstore.settings import Settings
from .uploads import MAX_CONFIG_BYTES
from .zip_safety import MB

#: multipart part headers and boundaries on top of the dataset and config parts
ENVELOPE_BYTES = 64 * 1024


def upload_body_cap(settings: Settings) -> int:
    return int(settings.max_upload_mb * MB) + MAX_CONFIG_BYTES + ENVELOPE_BYTES


def upload_too_large(settings: Settings) -> ApiError:
    return ApiError(413, "upload_too_large",
                    f"request body exceeds the {settings.max_upload_mb:g} MB upload cap (NEPF_MAX_UPLOAD_MB)")


def route_path(scope: Scope) -> str:
    """The path the router matches: ``path`` without the ``root_path`` a proxy may prefix."""
    path, root = scope.get("path", ""), scope.get("root_path", "")
    return path[len(root):] if root and path.startswith(root) else path


class BodyLimit:
    """Pure ASGI middleware: ``caps`` maps ``(method, path)`` to its body cap in bytes; other
    requests pass through untouched. ``error()`` builds the 413 raised past a cap."""

    def __init__(self, app: ASGIApp, *, caps: dict[tuple[str, str], int], error: Callable[[], ApiError]) -> None:
        self.app = app
        self.caps = caps
        self.error = error

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        cap = self.caps.get((scope.get("method", ""), route_path(scope))) if scope["type"] == "http" else None
        if cap is None:
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length", b"")
        if declared.isdigit() and int(declared) > cap:
            err = self.error()
            await JSONResponse(err.body(), status_code=err.status, headers={"Connection": "close"})(
                scope, receive, send)
            return
        received = 0
        body_complete = False

        async def counted_receive() -> Message:
            nonlocal received, body_complete
            if received > cap:      # the app asked again after the refusal: still no more reading
                raise self.error()
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                body_complete = not message.get("more_body", False)
                if received > cap:
                    raise self.error()
            return message

        async def closing_send(message: Message) -> None:
            if message["type"] == "http.response.start" and not body_complete:
                message = {**message, "headers": [*message.get("headers", []), (b"connection", b"close")]}
            await send(message)

        await self.app(scope, counted_receive, closing_send)
