"""One error shape for every 4xx/5xx the API produces on purpose.

Body: ``{"detail": "<human message>", "code": "<machine code>", "errors": [...]}`` where
``errors`` (dataset problems) are ``{"code", "message", "file", "view"}`` like the CLI's
``DatasetError.to_dict()``.
"""

from __future__ import annotations

from http import HTTPStatus
from typing import Any, Optional

from fastapi import Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match, Mount
from starlette.staticfiles import StaticFiles


class ApiError(Exception):
    def __init__(self, status: int, code: str, message: str, *, errors: Optional[list] = None,
                 headers: Optional[dict] = None) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.errors = errors or []
        self.headers = headers

    def body(self) -> dict[str, Any]:
        return {"detail": self.message, "code": self.code, "errors": self.errors}


async def api_error_handler(_request: Request, exc: ApiError) -> JSONResponse:
    return JSONResponse(exc.body(), status_code=exc.status, headers=exc.headers)


async def internal_error_handler(_request: Request, exc: Exception) -> JSONResponse:
    """Any exception no route turned into an :class:`ApiError` is a bug: a 500 in the API's
    error shape (``internal_error``) without the Python text. Starlette re-raises the exception
    after this answer, so the server logs it with its traceback (server-side only)."""
    body = ApiError(500, "internal_error", "internal server error (logged on the server)").body()
    return JSONResponse(body, status_code=500)


def not_found(what: str = "job") -> ApiError:
    return ApiError(404, "not_found", f"{what} not found")


#: methods probed when listing what a path allows
HTTP_METHODS = ("DELETE", "GET", "HEAD", "OPTIONS", "PATCH", "POST", "PUT")


def allowed_methods(routes, path: str, root_path: str = "") -> list[str]:
    """The methods the app answers on ``path``, found by asking each route whether it matches a
    probe request of each method (the router's own test, so included routers count too). The
    static catch-all mount (GET, HEAD) counts only where no API route knows the path: an API
    path lists its own methods (``/jobs/{id}/cancel``: POST), not the viewer's files'."""
    api: set[str] = set()
    static: set[str] = set()
    path_known = False
    for method in HTTP_METHODS:
        probe = {"type": "http", "method": method, "path": path, "root_path": root_path, "headers": []}
        for route in routes:
            match, _ = route.matches(probe)
            if match == Match.NONE:
                continue
            if isinstance(route, Mount) and isinstance(route.app, StaticFiles):
                static |= {method} & {"GET", "HEAD"}
                continue
            path_known = True
            if match == Match.FULL:
                api.add(method)
    return sorted(api if path_known else static)


def http_error_code(status: int) -> str:
    """``not_found`` for 404, ``bad_request`` for 400...: the status phrase as a code."""
    try:
        return HTTPStatus(status).phrase.lower().replace(" ", "_").replace("-", "_")
    except ValueError:
        return f"http_{status}"


async def http_error_handler(request: Request, exc: StarletteHTTPException):
    """Every ``HTTPException`` (an unknown API path, a file the static viewer does not have, a
    405) in the API's error shape, ``{"detail", "code", "errors"}``; FastAPI's own handler gave
    the viewer's 404s as ``{"detail": "Not Found"}`` (issue 37). A 405 lists every allowed method
    in ``Allow`` (Starlette's own lists only the first route that matched the path)."""
    if exc.status_code in (204, 304) or exc.status_code < 400:   # no body allowed / not an error
        return await http_exception_handler(request, exc)
    if exc.status_code != 405:
        detail = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        body = ApiError(exc.status_code, http_error_code(exc.status_code), detail).body()
        return JSONResponse(body, status_code=exc.status_code, headers=exc.headers)
    scope = request.scope
    allow = ", ".join(allowed_methods(request.app.routes, scope["path"], scope.get("root_path", "")))
    body = ApiError(405, "method_not_allowed", f"{request.method} is not allowed here; allowed: {allow}")
    return JSONResponse(body.body(), status_code=405, headers={**(exc.headers or {}), "Allow": allow})


async def storage_error_handler(_request: Request, exc: Exception) -> JSONResponse:
    """The object store did not answer (``jobstore.storage.StorageUnavailable``): a 503 the client
    may retry; the message names the store and its error, never the user's data."""
    body = ApiError(503, "storage_unavailable", f"the object store is unavailable, try again later ({exc})").body()
    return JSONResponse(body, status_code=503, headers={"Retry-After": "5"})
