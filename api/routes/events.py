"""``/jobs/{id}/events``: Server-Sent Events (FastAPI's ``EventSourceResponse`` frames them and
sends a keep-alive comment after 15 s of silence), and the short-lived ticket that lets an
``EventSource`` (which cannot send headers) open the stream."""

from __future__ import annotations

import asyncio
import json
from typing import Annotated, AsyncIterator, Optional

from fastapi import APIRouter, Depends, Header, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.sse import EventSourceResponse, ServerSentEvent

from jobstore.models import TERMINAL, Job
from jobstore.storage import StorageUnavailable

from ..auth import check_ticket, make_ticket
from ..deps import CredsDep, OwnerDep, ServiceDep, owner_from_header
from ..errors import ApiError
from ..queries import find_job, load_job, to_public
from ..schemas import ErrorBody, Ticket

router = APIRouter(tags=["jobs"])
ERRORS = {401: {"model": ErrorBody, "description": "Missing or invalid token"},
          404: {"model": ErrorBody, "description": "No such job for this owner"}}
#: how often the stream looks at the job and its metrics file
POLL_S = 0.5
#: the reconnection delay the stream asks of the browser
RETRY_MS = 2000


@router.post("/jobs/{job_id}/events/ticket", response_model=Ticket, responses=ERRORS,
             summary="A short-lived signed ticket for EventSource (which cannot send headers)")
def events_ticket(job_id: str, svc: ServiceDep, owner: OwnerDep, creds: CredsDep):
    job = load_job(svc, owner, job_id)
    token_id = svc.verifier.token_id(creds.credentials) if creds is not None else None
    if token_id is None:   # revoked between the (cached) check of the route and now
        raise ApiError(401, "unauthorized", "missing or invalid bearer token", headers={"WWW-Authenticate": "Bearer"})
    t = make_ticket(svc.secret, owner, job.id, token_id)
    return Ticket(ticket=t, expires_in=svc.settings.ticket_ttl_s, url=f"/jobs/{job.id}/events?ticket={t}")


async def stream_owner(job_id: str, svc: ServiceDep, creds: CredsDep,
                       ticket: Annotated[Optional[str], Query(max_length=1024)] = None) -> str:
    """The caller of the stream: a bearer token, or a valid ticket for this job whose token is
    still live now, at connect time (checked uncached). A dependency, so that a refusal is a
    401 before the stream starts."""
    owner = owner_from_header(svc, creds)
    if owner is None and ticket:
        claims = check_ticket(svc.secret, ticket, job_id, svc.settings.ticket_ttl_s)
        if claims is not None and await run_in_threadpool(svc.verifier.token_is_live, claims[1], claims[0]):
            owner = claims[0]
    if owner is None:
        raise ApiError(401, "unauthorized", "missing or invalid bearer token or ticket",
                       headers={"WWW-Authenticate": "Bearer"})
    return owner


async def stream_job(job_id: str, svc: ServiceDep, owner: Annotated[str, Depends(stream_owner)]) -> Job:
    return await run_in_threadpool(load_job, svc, owner, job_id)


def _event(event: str, data: dict, eid: Optional[int] = None) -> ServerSentEvent:
    return ServerSentEvent(event=event, raw_data=json.dumps(data, separators=(",", ":")),
                           id=str(eid) if eid is not None else None)


def progress_state(job: Job) -> dict:
    """What a ``progress`` event carries (sent again only when it changes)."""
    pub = to_public(job).model_dump(mode="json")
    return {k: pub[k] for k in ("status", "progress", "error", "decisions", "cancel_requested")}


def new_metrics(svc, job_id: str, cursor: int) -> tuple[list[dict], int]:
    """The records after ``cursor`` and the next cursor. While the object store does not answer
    there are none: the stream goes on with the job's progress, and the records come once it is back."""
    try:
        return svc.storage.read_metrics(job_id, cursor, 1000)
    except StorageUnavailable:
        return [], cursor


@router.get("/jobs/{job_id}/events", responses={**ERRORS, 200: {"content": {"text/event-stream": {}},
                                                                 "description": "Server-Sent Events"}},
            response_class=EventSourceResponse,
            summary="Server-Sent Events: progress, status and new metric records")
async def job_events(request: Request, svc: ServiceDep, job: Annotated[Job, Depends(stream_job)],
                     since: Annotated[Optional[int], Query(ge=0, le=1_000_000_000)] = None,
                     last_event_id: Annotated[Optional[str], Header(alias="Last-Event-ID")] = None
                     ) -> AsyncIterator[ServerSentEvent]:
    """``progress`` when the job's state changes, one ``metrics`` event per new record (its id is
    the metrics cursor, so ``Last-Event-ID`` resumes), ``end`` with the final status."""
    cursor = int(last_event_id) if last_event_id and last_event_id.isdigit() else (since or 0)
    yield ServerSentEvent(retry=RETRY_MS)
    last = None
    while not await request.is_disconnected():
        cur = await run_in_threadpool(find_job, svc.Session, job.owner, job.id)
        if cur is None:
            yield _event("end", {"status": "deleted"})
            return
        recs, nxt = await run_in_threadpool(new_metrics, svc, job.id, cursor)
        for i, rec in enumerate(recs):
            yield _event("metrics", rec, cursor + i + 1)
        cursor = nxt
        state = progress_state(cur)
        if state != last:
            yield _event("progress", state)
            last = state
        if cur.status in TERMINAL and not recs:
            yield _event("end", {"status": cur.status})
            return
        await asyncio.sleep(POLL_S)
