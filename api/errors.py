"""One error shape for every 4xx/5xx the API produces on purpose.

Body: ``{"detail": "<human message>", "code": "<machine code>", "errors": [...]}`` where
``errors`` (dataset problems) are ``{"code", "message", "file", "view"}`` like the CLI's
``DatasetError.to_dict()``.
"""

from __future__ import annotations

from typing import Any, Optional

from fastapi import Request
from fastapi.responses import JSONResponse


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


def not_found(what: str = "job") -> ApiError:
    return ApiError(404, "not_found", f"{what} not found")
