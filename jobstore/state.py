"""Every change of a job's state, each one conditional ``UPDATE`` (atomic on SQLite and PostgreSQL).

The life of a job::

    queued --claim--> running --finish--> succeeded | failed | cancelled
      ^  \\              |  \\
      |   cancel         |   requeue (worker shutdown: back to queued, "interrupted")
      |                  heartbeat (lease, progress, cancel flag)
      +--- reserve_resend (reconciler: a lost message or an expired lease)

Who calls what: the API inserts a job, marks it sent (:func:`mark_sent`), cancels it
(:func:`cancel`) and deletes it (:func:`delete_finished`); the worker claims, beats, finishes or
requeues it (:class:`~worker.runner.JobRunner`); the reconciler re-sends it
(:func:`reserve_resend`, :func:`release_resend`). A condition that no longer holds (another
worker holds the lease, the job finished meanwhile) makes the ``UPDATE`` touch no row, and the
caller is told so instead of overwriting someone else's state.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any, Optional

from sqlalchemy import or_, select, update
from sqlalchemy.orm import sessionmaker

from .models import ACTIVE, TERMINAL, Job, utcnow


def _held_by(job_id: str, worker_id: str):
    """The condition of every worker write: this worker holds the lease of a running job."""
    return (Job.id == job_id, Job.lease_owner == worker_id, Job.status == "running")


# ------------------------------------------------------------------------------ worker
@dataclass
class Claim:
    """What :func:`claim` found: ``outcome`` is ``claimed``, ``gave_up`` (past the redelivery
    cap: the job is failed), ``finished``, ``held`` (another worker's live lease), ``cancelled``
    or ``missing``; ``total`` is the job's last known step count."""

    outcome: str
    total: Optional[int] = None


def claim(Session: sessionmaker, job_id: str, worker_id: str, *, lease_s: float, max_deliveries: int,
          resume_step: int = 0) -> Claim:
    """Move a queued (or lease-expired running) job that is not cancelled to ``running`` under
    ``worker_id``'s lease, counting the attempt. ``resume_step`` > 0 (a checkpoint exists): the
    job shows ``resuming`` at that step. A cancel requested while nobody held the job ends it."""
    now = utcnow()
    start = {"stage": "resuming", "step": resume_step} if resume_step else {"stage": "starting"}
    with Session() as s:
        res = s.execute(
            update(Job)
            .where(Job.id == job_id, Job.status.in_(ACTIVE), Job.cancel_requested == False,  # noqa: E712
                   (Job.lease_owner.is_(None)) | (Job.lease_expires < now))
            .values(status="running", lease_owner=worker_id, lease_expires=now + dt.timedelta(seconds=lease_s),
                    attempts=Job.attempts + 1, error=None, **start))
        s.commit()
        job = s.get(Job, job_id)
        if job is None:
            return Claim("missing")
        if res.rowcount != 1:
            return Claim(_not_claimed(s, job, now))
        values: dict[str, Any] = {"attempt_log": list(job.attempt_log or []) + [
            {"worker": worker_id, "claimed_at": now.isoformat() + "Z", "first_step": None}]}
        total = job.total or None
        if resume_step and total:
            values["fraction"] = min(1.0, resume_step / total)
        if job.started_at is None:
            values["started_at"] = now
        if job.attempts > max_deliveries:
            values.update(status="failed", finished_at=now, lease_owner=None, lease_expires=None,
                          stage="failed", completions=Job.completions + 1,
                          error=(f"the job was interrupted {job.attempts - 1} times (its worker crashed "
                                 f"or was killed); giving up after NEPF_MAX_DELIVERIES={max_deliveries}"))
        s.execute(update(Job).where(Job.id == job_id, Job.lease_owner == worker_id).values(**values))
        s.commit()
        return Claim("gave_up" if "finished_at" in values else "claimed", total)


def _not_claimed(s, job: Job, now: dt.datetime) -> str:
    if job.status in TERMINAL:
        return "finished"
    if job.cancel_requested and (job.lease_owner is None or job.lease_expires < now):
        s.execute(update(Job).where(Job.id == job.id, Job.status.in_(ACTIVE))
                  .values(status="cancelled", finished_at=now, stage="cancelled", lease_owner=None,
                          lease_expires=None))
        s.commit()
        return "cancelled"
    return "held"


@dataclass
class Beat:
    """What :func:`heartbeat` found: ``held`` (False: the lease was lost) and the cancel flag."""

    held: bool
    cancel_requested: bool = False


def heartbeat(Session: sessionmaker, job_id: str, worker_id: str, *, lease_s: float,
              values: Optional[dict] = None, first_step: Optional[int] = None) -> Beat:
    """Renew the lease, write ``values`` (progress, decisions), record the attempt's first step
    once, and read the cancel flag; all only while ``worker_id`` holds the running job."""
    values = {**(values or {}), "lease_expires": utcnow() + dt.timedelta(seconds=lease_s)}
    with Session() as s:
        res = s.execute(update(Job).where(*_held_by(job_id, worker_id)).values(**values))
        if res.rowcount != 1:
            s.rollback()
            return Beat(False)
        if first_step is not None:
            _mark_attempt(s, job_id, worker_id, first_step=first_step)
        cancel = bool(s.execute(select(Job.cancel_requested).where(Job.id == job_id)).scalar())
        s.commit()
        return Beat(True, cancel)


def _mark_attempt(s, job_id: str, worker_id: str, **fields) -> Optional[list]:
    """``attempt_log`` with ``fields`` merged into this worker's last entry (written here)."""
    job = s.get(Job, job_id)
    logs = list(job.attempt_log or []) if job is not None else []
    if logs and logs[-1].get("worker") == worker_id:
        logs[-1] = {**logs[-1], **fields}
        s.execute(update(Job).where(Job.id == job_id).values(attempt_log=logs))
    return logs


def finish(Session: sessionmaker, job_id: str, worker_id: str, status: str, values: dict) -> bool:
    """Record the outcome once: ``status`` plus ``values`` (error, result, last progress), the
    lease released and ``completions`` counted. False when the lease was lost first."""
    values = dict(values, status=status, finished_at=utcnow(), lease_owner=None, lease_expires=None,
                  completions=Job.completions + 1, stage=status)
    with Session() as s:
        res = s.execute(update(Job).where(*_held_by(job_id, worker_id)).values(**values))
        s.commit()
    return res.rowcount == 1


def requeue(Session: sessionmaker, job_id: str, worker_id: str) -> bool:
    """Give a running job back after a worker shutdown: ``queued``, stage ``interrupted``, lease
    released, ``enqueued_at`` cleared (the next reconcile pass re-sends it), the attempt not
    counted against the redelivery cap but kept in ``attempt_log`` as ``interrupted``."""
    with Session() as s:
        job = s.get(Job, job_id)
        logs = list(job.attempt_log or []) if job is not None else []
        if logs and logs[-1].get("worker") == worker_id:
            logs[-1] = {**logs[-1], "interrupted": "worker shutdown"}
        res = s.execute(update(Job).where(*_held_by(job_id, worker_id))
                        .values(status="queued", stage="interrupted", lease_owner=None, lease_expires=None,
                                enqueued_at=None, attempts=Job.attempts - 1, attempt_log=logs))
        s.commit()
    return res.rowcount == 1


# ------------------------------------------------------------------------------ API
def mark_sent(Session: sessionmaker, job_id: str) -> None:
    """The API sent the job's first message (the reconciler sends those it could not)."""
    with Session() as s:
        s.execute(update(Job).where(Job.id == job_id, Job.enqueued_at.is_(None))
                  .values(enqueued_at=utcnow(), enqueue_count=Job.enqueue_count + 1))
        s.commit()


def cancel(Session: sessionmaker, job_id: str) -> Optional[Job]:
    """A queued job nobody holds is cancelled at once; an active one gets the flag its worker
    reads at the next heartbeat. Returns the job as it is now (None: gone)."""
    with Session() as s:
        res = s.execute(update(Job).where(Job.id == job_id, Job.status == "queued", Job.lease_owner.is_(None))
                        .values(status="cancelled", cancel_requested=True, finished_at=utcnow(),
                                stage="cancelled"))
        if res.rowcount == 0:
            s.execute(update(Job).where(Job.id == job_id, Job.status.in_(ACTIVE)).values(cancel_requested=True))
        s.commit()
        return s.get(Job, job_id)


def delete_finished(Session: sessionmaker, job_id: str) -> bool:
    """Delete the row of a finished job; False while it is queued or running."""
    with Session() as s:
        res = s.execute(Job.__table__.delete().where(Job.id == job_id, Job.status.in_(TERMINAL)))
        s.commit()
    return res.rowcount == 1


# ------------------------------------------------------------------------------ reconciler
def unheld(Session: sessionmaker, now: dt.datetime) -> list:
    """Active jobs no live lease holds: ``(id, status, queue, enqueued_at, enqueue_count,
    created_at, stage)``."""
    with Session() as s:
        return s.execute(
            select(Job.id, Job.status, Job.queue, Job.enqueued_at, Job.enqueue_count, Job.created_at, Job.stage)
            .where(Job.status.in_(ACTIVE), or_(Job.lease_expires.is_(None), Job.lease_expires < now))).all()


def reserve_resend(Session: sessionmaker, job_id: str, seen_enqueued_at: Optional[dt.datetime],
                   was_running: bool, now: dt.datetime) -> bool:
    """Reserve one re-send of an unheld job (several reconcilers may race: only the one whose
    ``seen_enqueued_at`` still matches wins); a running job with an expired lease goes back to
    ``queued``, stage ``requeued``."""
    with Session() as s:
        res = s.execute(
            update(Job)
            .where(Job.id == job_id, Job.status.in_(ACTIVE),
                   or_(Job.lease_expires.is_(None), Job.lease_expires < now),
                   or_(Job.enqueued_at.is_(None), Job.enqueued_at == seen_enqueued_at))
            .values(status="queued", enqueued_at=now, enqueue_count=Job.enqueue_count + 1,
                    lease_owner=None, lease_expires=None, stage=("requeued" if was_running else Job.stage)))
        s.commit()
    return res.rowcount == 1


def release_resend(Session: sessionmaker, job_id: str) -> None:
    """The reserved send failed (broker down): not counted as a send; the next pass tries again."""
    with Session() as s:
        s.execute(update(Job).where(Job.id == job_id)
                  .values(enqueued_at=None, enqueue_count=Job.enqueue_count - 1))
        s.commit()
