"""``/jobs`` routes: create (the upload), list, read, metrics, cancel, delete. Another owner's
job is indistinguishable from a missing one (404). The SQL is in :mod:`api.queries` and
:mod:`jobstore.state`; the event stream in :mod:`api.routes.events`; the artifacts in
:mod:`api.routes.artifacts`."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path
from typing import Annotated, Optional

from fastapi import APIRouter, Header, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse, Response
from sqlalchemy.exc import IntegrityError

from jobstore import state
from jobstore.models import TERMINAL, Job, new_id, utcnow
from jobstore.queue import enqueue

from ..deps import OwnerDep, ServiceDep
from ..errors import ApiError
from ..job_config import job_config_schema, parse_config, resolve_holdout_every
from ..queries import find_by_idempotency_key, get_job, insert_job, list_jobs as query_jobs, load_job, to_public
from ..schemas import ErrorBody, JobList, JobPublic, MetricsPage
from ..uploads import check_images, dataset_root, receive_multipart, validate_dataset
from ..zip_safety import MB, check_and_extract_zip

log = logging.getLogger("nepf.api")
router = APIRouter(tags=["jobs"])

ERRORS = {401: {"model": ErrorBody, "description": "Missing or invalid token"},
          404: {"model": ErrorBody, "description": "No such job for this owner"}}


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
                "config": {"type": "string",
                           "description": "A JSON object of job options, every key optional: see the JobConfig "
                                          "schema (GET /schemas/job-config gives it with this server's limits)."},
            }}}},
    }
}


@router.get("/schemas/job-config", tags=["jobs"], responses=ERRORS,
            summary="The JSON schema of a job's config, with this server's default preset and image-side ceiling")
def get_job_config_schema(svc: ServiceDep, owner: OwnerDep) -> dict:
    return job_config_schema(svc.settings)


def _check_idempotency_key(key: Optional[str]) -> None:
    if key is not None and not (0 < len(key) <= 200 and key.isprintable()):
        raise ApiError(422, "invalid_idempotency_key", "Idempotency-Key must be 1-200 printable characters")


def _validated_dataset(up, staging: Path, settings, cfg: dict) -> tuple[Path, dict]:
    """Unpack and check the upload (zip, images, the core's validator): ``(dataset root, summary)``."""
    extract = staging / "extract"
    members = check_and_extract_zip(up.zip_path, extract, settings)
    up.zip_path.unlink()
    check_images(extract, members, settings)
    root = dataset_root(extract)
    return root, validate_dataset(root, settings, settings.job_max_side(cfg.get("max_image_side")))


@router.post("/jobs", status_code=202, response_model=JobPublic, openapi_extra=MULTIPART_DOC,
             responses={**ERRORS, 409: {"model": ErrorBody}, 413: {"model": ErrorBody},
                        415: {"model": ErrorBody},
                        422: {"model": ErrorBody, "description": "Rejected upload or invalid dataset"},
                        507: {"model": ErrorBody, "description": "The server ran out of disk space"}},
             summary="Upload a dataset zip and queue a training job")
async def create_job(request: Request, svc: ServiceDep, owner: OwnerDep,
                     idempotency_key: Annotated[Optional[str], Header(alias="Idempotency-Key")] = None):
    settings = svc.settings
    _check_idempotency_key(idempotency_key)
    staging = settings.uploads_path / new_id()
    staging.mkdir(parents=True)
    try:
        # the whole body is capped by api.body_limit; the dataset part here
        up = await receive_multipart(request.stream(), request.headers.get("content-type", ""), staging,
                                     int(settings.max_upload_mb * MB))
        cfg = parse_config(up.config_raw, settings)
        if idempotency_key:
            existing = await run_in_threadpool(find_by_idempotency_key, svc.Session, owner, idempotency_key)
            if existing is not None:
                return _replay(existing, up.sha256)
        root, summary = await run_in_threadpool(_validated_dataset, up, staging, settings, cfg)
        cfg, summary = resolve_holdout_every(cfg, summary)
        return await _queue_job(svc, owner, root, cfg, summary, idempotency_key, up.sha256)
    finally:
        shutil.rmtree(staging, ignore_errors=True)


async def _queue_job(svc, owner: str, root: Path, cfg: dict, summary: dict, idempotency_key: Optional[str],
                     sha256: str) -> JSONResponse:
    """Store the validated dataset as a new job's (:mod:`jobstore.storage`), insert the job and send
    it. The dataset is stored before the row is inserted, so a job row always has its whole
    dataset; a job that is not inserted leaves no files behind."""
    settings = svc.settings
    job_id = new_id()
    try:
        await run_in_threadpool(svc.storage.put_dataset, job_id, root)
        job = Job(id=job_id, owner=owner, name=cfg.get("name"), status="queued", config=cfg,
                  dataset={k: v for k, v in summary.items() if k != "ok"}, queue=settings.job_queue,
                  idempotency_key=idempotency_key, request_hash=sha256, created_at=utcnow(), attempt_log=[])
        await run_in_threadpool(insert_job, svc.Session, job)
    except IntegrityError:
        # a concurrent request with the same Idempotency-Key won the race
        await run_in_threadpool(_delete_quietly, svc, job_id)
        existing = await run_in_threadpool(find_by_idempotency_key, svc.Session, owner, idempotency_key or "")
        if existing is None:
            raise
        return _replay(existing, sha256)
    except BaseException:
        await run_in_threadpool(_delete_quietly, svc, job_id)
        raise
    await run_in_threadpool(_send, svc, job_id, settings.job_queue)
    job = await run_in_threadpool(get_job, svc.Session, job_id)
    return json_response(to_public(job), 202, {"Location": f"/jobs/{job_id}"})


def _delete_quietly(svc, job_id: str) -> None:
    """Remove the files of a job that was never inserted; the request fails or is replayed anyway,
    so a store that does not answer is only logged."""
    try:
        svc.storage.delete_job(job_id)
    except Exception as exc:  # noqa: BLE001
        log.warning("could not delete the files of the rejected job %s: %s", job_id, exc)


def _send(svc, job_id: str, queue: str) -> None:
    try:
        enqueue(svc.celery, job_id, queue)
    except Exception as exc:  # noqa: BLE001 - the reconciler sends it once the broker is back
        log.warning("enqueue of %s failed (%s); the reconciler will retry", job_id, exc)
        return
    state.mark_sent(svc.Session, job_id)


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
    total, rows = query_jobs(svc.Session, owner, status, limit, offset)
    nxt = None
    if offset + len(rows) < total:
        nxt = f"/jobs?limit={limit}&offset={offset + limit}" + (f"&status={status}" if status else "")
    return JobList(items=[to_public(j) for j in rows], total=total, limit=limit, offset=offset, next=nxt)


@router.get("/jobs/{job_id}", response_model=JobPublic, responses=ERRORS, summary="One job")
async def get_one_job(job_id: str, svc: ServiceDep, owner: OwnerDep):
    body = svc.job_cache.get(job_id, owner)
    if body is None:
        job = await run_in_threadpool(load_job, svc, owner, job_id)
        body = json.dumps(to_public(job).model_dump(mode="json"), separators=(",", ":")).encode()
        svc.job_cache.put(job_id, owner, body)
    return Response(body, media_type="application/json")


@router.get("/jobs/{job_id}/metrics", response_model=MetricsPage, responses=ERRORS,
            summary="Metric series (metrics.jsonl); ?since=<next_since> returns only new records")
def get_metrics(job_id: str, svc: ServiceDep, owner: OwnerDep,
                since: Annotated[int, Query(ge=0, le=1_000_000_000)] = 0,
                limit: Annotated[int, Query(ge=1, le=100_000)] = 10_000):
    job = load_job(svc, owner, job_id)
    recs, nxt = svc.storage.read_metrics(job.id, since, limit)
    return MetricsPage(records=recs, since=since, next_since=nxt, status=job.status)


# ------------------------------------------------------------------------------- control
@router.post("/jobs/{job_id}/cancel", status_code=202, response_model=JobPublic,
             responses={**ERRORS, 409: {"model": ErrorBody}},
             summary="Cooperative cancel: training stops at its next step; partial exports stay")
def cancel_job(job_id: str, svc: ServiceDep, owner: OwnerDep):
    job = load_job(svc, owner, job_id)
    if job.status in TERMINAL:
        raise ApiError(409, "job_finished", f"job is already {job.status}")
    job = state.cancel(svc.Session, job.id)
    svc.job_cache.drop(job_id)
    return json_response(to_public(job), 202)


@router.delete("/jobs/{job_id}", status_code=204, responses={**ERRORS, 409: {"model": ErrorBody}},
               summary="Delete a finished job and its files")
def delete_job(job_id: str, svc: ServiceDep, owner: OwnerDep):
    job = load_job(svc, owner, job_id)
    if job.status not in TERMINAL:
        raise ApiError(409, "job_active", "job is still queued or running; cancel it first")
    # the files first (a finished job never runs again): a store that does not answer makes this a
    # 503 and the job stays, instead of a job gone with its objects left behind
    svc.storage.delete_job(job.id)
    if not state.delete_finished(svc.Session, job.id):
        raise ApiError(409, "job_active", "job is still queued or running; cancel it first")
    svc.job_cache.drop(job.id)
    return Response(status_code=204)

