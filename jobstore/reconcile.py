"""Reconciler: re-send jobs the DB says are queued or running but that no worker holds.

The DB is the source of truth; a broker message is only a wake-up call. Cases it repairs:

* a worker was ``kill -9``'d mid-job: its lease (renewed every heartbeat) expires, the job is
  sent again and the next worker resumes it from its last checkpoint;
* a queued job that no worker claimed within ``NEPF_RESEND_AFTER_S`` of its last send: its
  message may be lost (a Redis restart without persistence, a flushed queue, a message an
  embedded worker took before it crashed), so it is sent again, and again after twice as long
  each time (at most an hour apart) while it stays unclaimed;
* the API died between inserting a job and sending its message;
* a worker stopped by a shutdown (SIGTERM/SIGINT) gave its job back (``queued``, stage
  ``interrupted``, no message): it is sent again at once, and the next worker resumes it.

It never looks inside the broker. Sending twice is harmless: a worker *claims* a job with one
conditional UPDATE (status active, lease free) before running it, so a duplicate message is
acknowledged and dropped, and a job is completed at most once. Several API processes may run
the reconciler at once: each re-send is reserved with a conditional UPDATE on ``enqueued_at``
(:func:`jobstore.state.reserve_resend`).
"""

from __future__ import annotations

import datetime as dt
import logging
import threading
from typing import Callable, Optional

from sqlalchemy.orm import sessionmaker

from . import state
from .models import utcnow
from .queue import enqueue
from .settings import Settings

log = logging.getLogger("nepf.reconcile")

#: a job the API inserted less than this long ago and has not sent yet is still being sent
SENDING_GRACE = dt.timedelta(seconds=10)
#: the longest wait between two re-sends of a job that stays unclaimed
MAX_RESEND_INTERVAL_S = 3600.0


def resend_due(job, now: dt.datetime, settings: Settings) -> bool:
    """Whether an unheld active job (a row of :func:`jobstore.state.unheld`) should be sent again."""
    lease_grace = dt.timedelta(seconds=max(settings.lease_s, 1.0))
    if job.status == "running":      # its lease expired: its worker is gone
        return job.enqueued_at is None or job.enqueued_at <= now - lease_grace
    if job.enqueued_at is None:      # never sent, or given back by a stopping worker ("interrupted")
        return job.stage == "interrupted" or job.created_at <= now - SENDING_GRACE
    # sent, and nobody claimed it: wait resend_after_s, doubled by every earlier re-send
    sends = max(int(getattr(job, "enqueue_count", 1) or 1), 1)
    wait = min(settings.resend_after_s * 2 ** (sends - 1), MAX_RESEND_INTERVAL_S)
    return job.enqueued_at <= now - dt.timedelta(seconds=max(wait, settings.lease_s, 1.0))


def reconcile_once(settings: Settings, Session: sessionmaker, send: Callable[[str, str], None]) -> list[str]:
    """One pass; returns the ids it re-sent."""
    now = utcnow()
    resent: list[str] = []
    for job in state.unheld(Session, now):
        if not resend_due(job, now, settings):
            continue
        if not state.reserve_resend(Session, job.id, job.enqueued_at, job.status == "running", now):
            continue   # another reconciler took it, or a worker claimed it meanwhile
        try:
            send(job.id, job.queue)
        except Exception as exc:  # noqa: BLE001 - broker down; the next pass retries
            log.warning("re-queue of %s failed: %s", job.id, exc)
            state.release_resend(Session, job.id)
            continue
        resent.append(job.id)
        log.warning("re-queued job %s (was %s, no worker held it)", job.id, job.status)
    return resent


class Reconciler(threading.Thread):
    """Background pass every ``NEPF_RECONCILE_INTERVAL_S`` seconds inside the API process."""

    def __init__(self, settings: Settings, Session: sessionmaker, celery_app) -> None:
        super().__init__(name="nepf-reconciler", daemon=True)
        self.settings = settings
        self.Session = Session
        self.celery_app = celery_app
        self.stop_event = threading.Event()

    def send(self, job_id: str, queue: str) -> None:
        enqueue(self.celery_app, job_id, queue)

    def run(self) -> None:
        while not self.stop_event.wait(self.settings.reconcile_interval_s):
            try:
                reconcile_once(self.settings, self.Session, self.send)
            except Exception:  # noqa: BLE001 - never let the thread die
                log.exception("reconcile pass failed")

    def stop(self) -> None:
        self.stop_event.set()
