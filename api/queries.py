"""The API's reads and inserts of the job store (state changes are :mod:`jobstore.state`'s).

Every read is scoped to an owner: another owner's job is indistinguishable from a missing one.
"""

from __future__ import annotations

import datetime as dt
import re
from typing import Optional

from sqlalchemy import func, select
from sqlalchemy.orm import sessionmaker

from jobstore.models import Job

from .errors import not_found
from .schemas import JobPublic

JOB_ID = re.compile(r"^[0-9a-f]{32}$")


def find_job(Session: sessionmaker, owner: str, job_id: str) -> Optional[Job]:
    """The owner's job, or None (a malformed id is never looked up)."""
    if not JOB_ID.match(job_id or ""):
        return None
    with Session() as s:
        return s.execute(select(Job).where(Job.id == job_id, Job.owner == owner)).scalar_one_or_none()


def load_job(svc, owner: str, job_id: str) -> Job:
    """The owner's job; a 404 when it does not exist or is not theirs."""
    job = find_job(svc.Session, owner, job_id)
    if job is None:
        raise not_found()
    return job


def get_job(Session: sessionmaker, job_id: str) -> Optional[Job]:
    with Session() as s:
        return s.get(Job, job_id)


def list_jobs(Session: sessionmaker, owner: str, status: Optional[str], limit: int,
              offset: int) -> tuple[int, list[Job]]:
    """``(total, page)`` of the owner's jobs (optionally of one status), newest first."""
    with Session() as s:
        q = select(Job).where(Job.owner == owner)
        c = select(func.count()).select_from(Job).where(Job.owner == owner)
        if status:
            q = q.where(Job.status == status)
            c = c.where(Job.status == status)
        total = s.execute(c).scalar_one()
        rows = s.execute(q.order_by(Job.created_at.desc(), Job.id.desc()).limit(limit).offset(offset)).scalars().all()
    return total, list(rows)


def find_by_idempotency_key(Session: sessionmaker, owner: str, key: str) -> Optional[Job]:
    with Session() as s:
        return s.execute(select(Job).where(Job.owner == owner, Job.idempotency_key == key)).scalar_one_or_none()


def insert_job(Session: sessionmaker, job: Job) -> None:
    """Insert a new job row (an ``IntegrityError``: another request took its Idempotency-Key)."""
    with Session() as s:
        s.add(job)
        s.commit()


def _utc(d):
    """The DB stores naive UTC; the API says so explicitly."""
    return d.replace(tzinfo=dt.timezone.utc) if d is not None and d.tzinfo is None else d


def to_public(job: Job) -> JobPublic:
    base = f"/jobs/{job.id}"
    return JobPublic(
        id=job.id, name=job.name, status=job.status,
        progress={"step": job.step or 0, "total": job.total, "fraction": job.fraction or 0.0,
                  "stage": job.stage, "eta_s": job.eta_s, "wall_s": job.wall_s},
        created_at=_utc(job.created_at), started_at=_utc(job.started_at), finished_at=_utc(job.finished_at),
        error=job.error, config=dict(job.config or {}), dataset=job.dataset or {}, decisions=job.decisions,
        cancel_requested=bool(job.cancel_requested),
        delivery={"attempts": job.attempts or 0, "attempt_log": job.attempt_log or [],
                  "completions": job.completions or 0, "sends": job.enqueue_count or 0},
        links={"self": base, "metrics": f"{base}/metrics", "events": f"{base}/events",
               "events_ticket": f"{base}/events/ticket", "artifacts": f"{base}/artifacts",
               "cancel": f"{base}/cancel"})
