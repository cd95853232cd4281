"""``/jobs`` routes. Another owner's job is indistinguishable from a missing one (404)."""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import logging
import re
import shutil
import time
from typing import Annotated, Optional

from fastapi import APIRouter, Header, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response, StreamingResponse
from sqlalchemy import func, select, update
from sqlalchemy.exc import IntegrityError

from jobstore.models import ACTIVE, TERMINAL, Job, new_id, utcnow
from jobstore.queue import enqueue
from jobstore.storage import StorageUnavailable

from ..artifacts import CONTENT_TYPES, content_type_for  # noqa: F401 - importable from here (tests)
from ..auth import check_ticket, make_ticket
from ..deps import CredsDep, OwnerDep, ServiceDep, owner_from_header
from ..errors import ApiError, not_found
from ..schemas import ErrorBody, JobList, JobPublic, MetricsPage, Ticket
from ..job_config import parse_config, resolve_holdout_every
from ..uploads import check_images, dataset_root, receive_multipart, validate_dataset
from ..zip_safety import MB, check_and_extract_zip

log = logging.getLogger("nepf.api")
router = APIRouter(tags=["jobs"])
JOB_ID = re.compile(r"^[0-9a-f]{32}$")

ERRORS = {401: {"model": ErrorBody, "description": "Missing or invalid token"},
          404: {"model": ErrorBody, "description": "No such job for this owner"}}

def _utc(d):
    """The DB stores naive UTC; the API says so explicitly."""
    return d.replace(tzinfo=dt.timezone.utc) if d is not None and d.tzinfo is None else d


def to_public(job: Job) -> JobPublic:
    base = f"/jobs/{job.id}"
    cfg = dict(job.config or {})
    return JobPublic(
        id=job.id, name=job.name, status=job.status,
        progress={"step": job.step or 0, "total": job.total, "fraction": job.fraction or 0.0,
                  "stage": job.stage, "eta_s": job.eta_s, "wall_s": job.wall_s},
        created_at=_utc(job.created_at), started_at=_utc(job.started_at), finished_at=_utc(job.finished_at),
        error=job.error, config=cfg, dataset=job.dataset or {}, decisions=job.decisions,
        cancel_requested=bool(job.cancel_requested),
        delivery={"attempts": job.attempts or 0, "attempt_log": job.attempt_log or [],
                  "completions": job.completions or 0, "sends": job.enqueue_count or 0},
        links={"self": base, "metrics": f"{base}/metrics", "events": f"{base}/events",
               "events_ticket": f"{base}/events/ticket", "artifacts": f"{base}/artifacts",
               "cancel": f"{base}/cancel"})


def _load(svc, owner: str, job_id: str) -> Job:
    if not JOB_ID.match(job_id or ""):
        raise not_found()
    with svc.Session() as s:
        job = s.execute(select(Job).where(Job.id == job_id, Job.owner == owner)).scalar_one_or_none()
    if job is None:
        raise not_found()
    return job


def json_response(model, status: int = 200, headers: Optional[dict] = None) -> JSONResponse:
    return JSONResponse(model.model_dump(mode="json"), status_code=status, headers=headers)


# ------------------------------------------------------------------------------- create
MULTIPART_DOC = {
    "requestBody": {
        "required": True,
        "content": {"multipart/form-data": {"schema": {
            "type": "object", "required": ["dataset"],
            "properties": {
                "dataset": {"type": "string", "format": "binary",
                            "description": "A .zip of a DTU, Blender or instant-ngp dataset folder."},
                "config": {"type": "string", "description":
                           'JSON object: {"preset": "fast|paper|tiny", "iters": int, '
                           '"time_budget_s": number, "name": str, "max_image_side": int (<= NEPF_MAX_IMAGE_SIDE), '
                           '"holdout_every": 0 or 2..n_views/2 (default 8 for 16+ views, else 0), '
                           '"texture_size": 256|512|1024|2048, "max_faces": 1000..2000000, '
                           '"up_axis": "auto|+x|-x|+y|-y|+z|-z"}; see JobConfig'},
            }}}},
    }
}


@router.post("/jobs", status_code=202, response_model=JobPublic, openapi_extra=MULTIPART_DOC,
             responses={**ERRORS, 409: {"model": ErrorBody}, 413: {"model": ErrorBody},
                        415: {"model": ErrorBody},
                        422: {"model": ErrorBody, "description": "Rejected upload or invalid dataset"},
                        507: {"model": ErrorBody, "description": "The server ran out of disk space"}},
             summary="Upload a dataset zip and queue a training job")
async def create_job(request: Request, svc: ServiceDep, owner: OwnerDep,
                     idempotency_key: Annotated[Optional[str], Header(alias="Idempotency-Key")] = None):
    settings = svc.settings
    if idempotency_key is not None and not (0 < len(idempotency_key) <= 200 and idempotency_key.isprintable()):
        raise ApiError(422, "invalid_idempotency_key", "Idempotency-Key must be 1-200 printable characters")
    max_bytes = int(settings.max_upload_mb * MB)   # the whole body is capped by api.body_limit
    staging = settings.uploads_path / new_id()
    staging.mkdir(parents=True)
    stored: Optional[str] = None   # a job id whose files were stored but not committed
    try:
        up = await receive_multipart(request.stream(), request.headers.get("content-type", ""), staging, max_bytes)
        cfg = parse_config(up.config_raw, settings)
        if idempotency_key:
            existing = await run_in_threadpool(_find_idem, svc, owner, idempotency_key)
            if existing is not None:
                return _replay(existing, up.sha256)

        def heavy():
            extract = staging / "extract"
            members = check_and_extract_zip(up.zip_path, extract, settings)
            up.zip_path.unlink()
            check_images(extract, members, settings)
            root = dataset_root(extract)
            return root, validate_dataset(root, settings, settings.job_max_side(cfg.get("max_image_side")))

        root, summary = await run_in_threadpool(heavy)
        cfg, summary = resolve_holdout_every(cfg, summary)
        job_id = new_id()
        stored = job_id
        # before the job row: a job row always has its whole dataset (in the data dir or the bucket)
        await run_in_threadpool(svc.storage.put_dataset, job_id, root)
        summary = {k: v for k, v in summary.items() if k != "ok"}
        job = Job(id=job_id, owner=owner, name=cfg.get("name"), status="queued", config=cfg, dataset=summary,
                  queue=settings.job_queue, idempotency_key=idempotency_key, request_hash=up.sha256,
                  created_at=utcnow(), attempt_log=[])

        def insert():
            with svc.Session() as s:
                s.add(job)
                s.commit()
        try:
            await run_in_threadpool(insert)
        except IntegrityError:
            # a concurrent request with the same Idempotency-Key won the race
            await run_in_threadpool(svc.storage.delete_job, job_id)
            stored = None
            existing = await run_in_threadpool(_find_idem, svc, owner, idempotency_key or "")
            if existing is None:
                raise
            return _replay(existing, up.sha256)
        stored = None  # committed: keep it
        await run_in_threadpool(_send, svc, job_id, settings.job_queue)
        with svc.Session() as s:
            job = s.get(Job, job_id)
        return json_response(to_public(job), 202, {"Location": f"/jobs/{job_id}"})
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        if stored is not None:
            await run_in_threadpool(_delete_quietly, svc, stored)


def _delete_quietly(svc, job_id: str) -> None:
    try:
        svc.storage.delete_job(job_id)
    except Exception as exc:  # noqa: BLE001 - the request fails anyway; say so in the log
        log.warning("could not delete the files of the rejected job %s: %s", job_id, exc)


def _send(svc, job_id: str, queue: str) -> None:
    try:
        enqueue(svc.celery, job_id, queue)
    except Exception as exc:  # noqa: BLE001 - the reconciler sends it once the broker is back
        log.warning("enqueue of %s failed (%s); the reconciler will retry", job_id, exc)
        return
    with svc.Session() as s:
        s.execute(update(Job).where(Job.id == job_id, Job.enqueued_at.is_(None))
                  .values(enqueued_at=utcnow(), enqueue_count=Job.enqueue_count + 1))
        s.commit()


def _find_idem(svc, owner: str, key: str) -> Optional[Job]:
    with svc.Session() as s:
        return s.execute(select(Job).where(Job.owner == owner, Job.idempotency_key == key)).scalar_one_or_none()


def _replay(existing: Job, sha: str) -> JSONResponse:
    if existing.request_hash and existing.request_hash != sha:
        raise ApiError(409, "idempotency_key_reused",
                       "this Idempotency-Key was already used with a different upload or config")
    return json_response(to_public(existing), 202,
                         {"Location": f"/jobs/{existing.id}", "Idempotent-Replayed": "true"})


# ------------------------------------------------------------------------------- read
@router.get("/jobs", response_model=JobList, responses=ERRORS, summary="The caller's jobs, newest first")
def list_jobs(svc: ServiceDep, owner: OwnerDep,
              limit: Annotated[int, Query(ge=1, le=100)] = 20,
              offset: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0,
              status: Annotated[Optional[str], Query(pattern="^(queued|running|succeeded|failed|cancelled)$")] = None):
    with svc.Session() as s:
        q = select(Job).where(Job.owner == owner)
        c = select(func.count()).select_from(Job).where(Job.owner == owner)
        if status:
            q = q.where(Job.status == status)
            c = c.where(Job.status == status)
        total = s.execute(c).scalar_one()
        rows = s.execute(q.order_by(Job.created_at.desc(), Job.id.desc()).limit(limit).offset(offset)).scalars().all()
    nxt = None
    if offset + len(rows) < total:
        nxt = f"/jobs?limit={limit}&offset={offset + limit}" + (f"&status={status}" if status else "")
    return JobList(items=[to_public(j) for j in rows], total=total, limit=limit, offset=offset, next=nxt)


@router.get("/jobs/{job_id}", response_model=JobPublic, responses=ERRORS, summary="One job")
async def get_job(job_id: str, svc: ServiceDep, owner: OwnerDep):
    body = svc.job_cache.get(job_id, owner)
    if body is None:
        job = await run_in_threadpool(_load, svc, owner, job_id)
        body = json.dumps(to_public(job).model_dump(mode="json"), separators=(",", ":")).encode()
        svc.job_cache.put(job_id, owner, body)
    return Response(body, media_type="application/json")


@router.get("/jobs/{job_id}/metrics", response_model=MetricsPage, responses=ERRORS,
            summary="Metric series (metrics.jsonl); ?since=<next_since> returns only new records")
def get_metrics(job_id: str, svc: ServiceDep, owner: OwnerDep,
                since: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0,
                limit: Annotated[int, Query(ge=1, le=100_000)] = 10_000):
    job = _load(svc, owner, job_id)
    recs, nxt = svc.storage.read_metrics(job.id, since, limit)
    return MetricsPage(records=recs, since=since, next_since=nxt, status=job.status)


# ------------------------------------------------------------------------------- events (SSE)
@router.post("/jobs/{job_id}/events/ticket", response_model=Ticket, responses=ERRORS,
             summary="A short-lived signed ticket for EventSource (which cannot send headers)")
def events_ticket(job_id: str, svc: ServiceDep, owner: OwnerDep, creds: CredsDep):
    job = _load(svc, owner, job_id)
    token_id = svc.verifier.token_id(creds.credentials) if creds is not None else None
    if token_id is None:   # revoked between the (cached) check of the route and now
        raise ApiError(401, "unauthorized", "missing or invalid bearer token", headers={"WWW-Authenticate": "Bearer"})
    t = make_ticket(svc.secret, owner, job.id, svc.settings.ticket_ttl_s, token_id)
    return Ticket(ticket=t, expires_in=svc.settings.ticket_ttl_s, url=f"/jobs/{job.id}/events?ticket={t}")


def _sse(event: str, data: dict, eid: Optional[int] = None) -> str:
    head = f"id: {eid}\n" if eid is not None else ""
    return f"{head}event: {event}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


@router.get("/jobs/{job_id}/events", responses={**ERRORS, 200: {"content": {"text/event-stream": {}},
                                                                 "description": "Server-Sent Events"}},
            response_class=StreamingResponse,
            summary="Server-Sent Events: progress, status and new metric records")
async def job_events(job_id: str, request: Request, svc: ServiceDep, creds: CredsDep,
                     ticket: Annotated[Optional[str], Query(max_length=1024)] = None,
                     since: Annotated[Optional[int], Query(ge=0, le=1_000_000_000)] = None,
                     last_event_id: Annotated[Optional[str], Header(alias="Last-Event-ID")] = None):
    owner = owner_from_header(svc, creds)
    if owner is None and ticket:
        claims = check_ticket(svc.secret, ticket, job_id)
        # the token the ticket was minted with must still be live now, at connect time
        if claims is not None and await run_in_threadpool(svc.verifier.token_is_live, claims[1], claims[0]):
            owner = claims[0]
    if owner is None:
        raise ApiError(401, "unauthorized", "missing or invalid bearer token or ticket",
                       headers={"WWW-Authenticate": "Bearer"})
    job = await run_in_threadpool(_load, svc, owner, job_id)
    cursor = since or 0
    if last_event_id and last_event_id.isdigit():
        cursor = int(last_event_id)
    poll = 0.5

    def load_state():
        with svc.Session() as s:
            return s.execute(select(Job).where(Job.id == job.id, Job.owner == owner)).scalar_one_or_none()

    async def gen():
        nonlocal cursor
        yield "retry: 2000\n\n"
        last = None
        keepalive = time.monotonic()
        while True:
            if await request.is_disconnected():
                return
            cur = await run_in_threadpool(load_state)
            if cur is None:
                yield _sse("end", {"status": "deleted"})
                return
            try:
                recs, nxt = await run_in_threadpool(svc.storage.read_metrics, job.id, cursor, 1000)
            except StorageUnavailable:   # the stream goes on; the records come once the store is back
                recs, nxt = [], cursor
            for i, rec in enumerate(recs):
                yield _sse("metrics", rec, cursor + i + 1)
            cursor = nxt
            pub = to_public(cur).model_dump(mode="json")
            state = {"status": pub["status"], "progress": pub["progress"], "error": pub["error"],
                     "decisions": pub["decisions"], "cancel_requested": pub["cancel_requested"]}
            if state != last:
                yield _sse("progress", state)
                last = state
                keepalive = time.monotonic()
            if cur.status in TERMINAL and not recs:
                yield _sse("end", {"status": cur.status})
                return
            if time.monotonic() - keepalive > 15:
                yield ": keepalive\n\n"
                keepalive = time.monotonic()
            await asyncio.sleep(poll)

    return StreamingResponse(gen(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


# ------------------------------------------------------------------------------- control
@router.post("/jobs/{job_id}/cancel", status_code=202, response_model=JobPublic,
             responses={**ERRORS, 409: {"model": ErrorBody}},
             summary="Cooperative cancel: training stops at its next step; partial exports stay")
def cancel_job(job_id: str, svc: ServiceDep, owner: OwnerDep):
    job = _load(svc, owner, job_id)
    if job.status in TERMINAL:
        raise ApiError(409, "job_finished", f"job is already {job.status}")
    now = utcnow()
    with svc.Session() as s:
        # a queued job nobody holds is cancelled at once; a running one at its next step
        res = s.execute(update(Job).where(Job.id == job.id, Job.status == "queued", Job.lease_owner.is_(None))
                        .values(status="cancelled", cancel_requested=True, finished_at=now, stage="cancelled"))
        if res.rowcount == 0:
            s.execute(update(Job).where(Job.id == job.id, Job.status.in_(ACTIVE)).values(cancel_requested=True))
        s.commit()
        job = s.get(Job, job.id)
    svc.job_cache.drop(job.id)
    return json_response(to_public(job), 202)


@router.delete("/jobs/{job_id}", status_code=204, responses={**ERRORS, 409: {"model": ErrorBody}},
               summary="Delete a finished job and its files")
def delete_job(job_id: str, svc: ServiceDep, owner: OwnerDep):
    job = _load(svc, owner, job_id)
    if job.status not in TERMINAL:
        raise ApiError(409, "job_active", "job is still queued or running; cancel it first")
    # files first (a finished job never runs again): if the store is down this is a 503 and the
    # job stays, instead of a job gone with its objects left behind
    svc.storage.delete_job(job.id)
    with svc.Session() as s:
        res = s.execute(Job.__table__.delete().where(Job.id == job.id, Job.status.in_(TERMINAL)))
        s.commit()
    if res.rowcount == 0:
        raise ApiError(409, "job_active", "job is still queued or running; cancel it first")
    svc.job_cache.drop(job.id)
    return Response(status_code=204)
