"""FastAPI dependencies: the caller's owner from ``Authorization: Bearer``."""

from __future__ import annotations

from typing import Annotated, Optional

from fastapi import Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from .errors import ApiError
from .service import Service, get_service

bearer = HTTPBearer(auto_error=False, description="A token from `nepf token create NAME`.")

UNAUTHORIZED = ApiError(401, "unauthorized", "missing or invalid bearer token",
                        headers={"WWW-Authenticate": "Bearer"})


def owner_from_header(svc: Service, creds: Optional[HTTPAuthorizationCredentials]) -> Optional[str]:
    if creds is None or creds.scheme.lower() != "bearer":
        return None
    return svc.verifier.owner_of(creds.credentials)


async def require_owner(svc: Annotated[Service, Depends(get_service)],
                        creds: Annotated[Optional[HTTPAuthorizationCredentials], Depends(bearer)]) -> str:
    owner = None
    if creds is not None and creds.scheme.lower() == "bearer":
        hit, owner = svc.verifier.cached(creds.credentials)
        if not hit:
            owner = await run_in_threadpool(svc.verifier.owner_of, creds.credentials)
    if owner is None:
        raise ApiError(401, "unauthorized", "missing or invalid bearer token",
                       headers={"WWW-Authenticate": "Bearer"})
    return owner


ServiceDep = Annotated[Service, Depends(get_service)]
OwnerDep = Annotated[str, Depends(require_owner)]
CredsDep = Annotated[Optional[HTTPAuthorizationCredentials], Depends(bearer)]


def base_url(request: Request) -> str:
    return str(request.base_url).rstrip("/")
