"""Reconciler: re-queue jobs the DB says are queued or running but that no worker holds.

The DB is the source of truth; a broker message is only a wake-up call. Cases it repairs:

* a worker was ``kill -9``'d mid-job: its lease (renewed every heartbeat) expires, the job is
  sent again and the next worker resumes it from its last checkpoint;
* the broker lost its messages (a Redis restart without persistence, a flushed queue): a
  queued job whose message is in no broker queue is sent again;
* the API died between inserting a job and sending its message;
* a worker stopped by a shutdown (SIGTERM/SIGINT) gave its job back (``queued``, stage
  ``interrupted``, no message): it is sent again at once, and the next worker resumes it.

Sending twice is harmless: a worker *claims* a job with one conditional UPDATE (status active,
lease free) before running it, so a duplicate message is acknowledged and dropped, and a job
is completed at most once. Several API processes may run the reconciler at once: each re-send
is reserved with a conditional UPDATE on ``enqueued_at``.
"""

from __future__ import annotations

import datetime as dt
import logging
import sqlite3
import threading
from typing import TYPE_CHECKING, Callable, Optional

from sqlalchemy import or_, select, update
from sqlalchemy.orm import sessionmaker

from .models import Job, utcnow
from .queue import QUEUES, enqueue

if TYPE_CHECKING:   # the settings object is passed in; the store never imports the API
    from api.settings import Settings

log = logging.getLogger("nepf.reconcile")


class BrokerView:
    """Which job ids have a message waiting in a broker queue (transport-specific, read-only)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings

    def waiting_job_ids(self) -> Optional[set[str]]:
        """Job ids mentioned by ready messages; None when the broker cannot be inspected."""
        try:
            if self.settings.embedded:
                return self._sqlite()
            url = self.settings.broker_url or ""
            if url.startswith(("redis://", "rediss://", "unix://")):
                return self._redis(url)
        except Exception as exc:  # noqa: BLE001 - broker down: try again next round
            log.warning("cannot inspect the broker: %s", exc)
            return None
        return None

    def _sqlite(self) -> set[str]:
        path = self.settings.data_path / "broker.sqlite3"
        if not path.exists():
            return set()
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=10)
        try:
            rows = con.execute("SELECT payload FROM kombu_message WHERE visible = 1").fetchall()
        except sqlite3.OperationalError:
            return set()
        finally:
            con.close()
        return _ids_in(r[0] if isinstance(r[0], str) else bytes(r[0]).decode("utf-8", "replace") for r in rows)

    def _redis(self, url: str) -> set[str]:
        import redis  # the py client Celery's redis transport already needs

        r = redis.Redis.from_url(url, socket_timeout=3, socket_connect_timeout=3)
        try:
            payloads = []
            for q in QUEUES:
                for key in [q] + [f"{q}\x06\x16{p}" for p in range(1, 10)]:
                    payloads.extend(r.lrange(key, 0, -1))
            return _ids_in(p.decode("utf-8", "replace") for p in payloads)
        finally:
            r.close()


def _ids_in(payloads) -> set[str]:
    import re

    ids: set[str] = set()
    for p in payloads:
        ids.update(re.findall(r"[0-9a-f]{32}", p))
    return ids


def reconcile_once(settings: Settings, Session: sessionmaker, send: Callable[[str, str], None],
                   broker: Optional[BrokerView] = None) -> list[str]:
    """One pass; returns the ids it re-sent."""
    now = utcnow()
    lease_grace = dt.timedelta(seconds=max(settings.lease_s, 1.0))
    broker = broker or BrokerView(settings)
    resent: list[str] = []
    with Session() as s:
        candidates = s.execute(
            select(Job.id, Job.status, Job.queue, Job.lease_expires, Job.enqueued_at, Job.created_at, Job.stage)
            .where(Job.status.in_(("queued", "running")))
            .where(or_(Job.lease_expires.is_(None), Job.lease_expires < now))
        ).all()
    if not candidates:
        return resent
    waiting = None
    if any(c.status == "queued" for c in candidates):
        waiting = broker.waiting_job_ids()
    for c in candidates:
        if c.status == "queued":
            if c.enqueued_at is None:
                # (a job a stopping worker gave back, stage "interrupted", goes at once)
                if c.stage != "interrupted" and c.created_at > now - dt.timedelta(seconds=10):
                    continue  # the API is still sending it
            elif waiting is None or c.id in waiting or c.enqueued_at > now - lease_grace:
                continue       # its message is waiting (or we cannot tell, or it was just sent)
        else:  # running with an expired lease: its worker is gone
            if c.enqueued_at is not None and c.enqueued_at > now - lease_grace:
                continue
        with Session() as s:
            # reserve the re-send (several reconcilers may race); a running job goes back to queued
            res = s.execute(
                update(Job)
                .where(Job.id == c.id, Job.status.in_(("queued", "running")),
                       or_(Job.lease_expires.is_(None), Job.lease_expires < now),
                       or_(Job.enqueued_at.is_(None), Job.enqueued_at == c.enqueued_at))
                .values(status="queued", enqueued_at=now, enqueue_count=Job.enqueue_count + 1,
                        lease_owner=None, lease_expires=None,
                        stage=("requeued" if c.status == "running" else Job.stage))
            )
            s.commit()
            if res.rowcount != 1:
                continue
        try:
            send(c.id, c.queue)
            resent.append(c.id)
            log.warning("re-queued job %s (was %s, no worker held it)", c.id, c.status)
        except Exception as exc:  # noqa: BLE001 - broker down; the next pass retries
            log.warning("re-queue of %s failed: %s", c.id, exc)
            with Session() as s:
                s.execute(update(Job).where(Job.id == c.id).values(enqueued_at=None))
                s.commit()
    return resent


class Reconciler(threading.Thread):
    """Background pass every ``NEPF_RECONCILE_INTERVAL_S`` seconds inside the API process."""

    def __init__(self, settings: Settings, Session: sessionmaker, celery_app) -> None:
        super().__init__(name="nepf-reconciler", daemon=True)
        self.settings = settings
        self.Session = Session
        self.celery_app = celery_app
        self.stop_event = threading.Event()
        self.broker = BrokerView(settings)

    def send(self, job_id: str, queue: str) -> None:
        enqueue(self.celery_app, job_id, queue)

    def run(self) -> None:
        while not self.stop_event.wait(self.settings.reconcile_interval_s):
            try:
                reconcile_once(self.settings, self.Session, self.send, self.broker)
            except Exception:  # noqa: BLE001 - never let the thread die
                log.exception("reconcile pass failed")

    def stop(self) -> None:
        self.stop_event.set()
