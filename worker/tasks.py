"""The Celery app of the worker and its one task, ``nepf.run_job`` (sent by name by the API)."""

from __future__ import annotations

import logging

from celery.signals import worker_ready

from api.db import session_factory
from api.queue import TASK_NAME, enqueue, make_celery
from api.reconcile import reconcile_once
from api.settings import get_settings

from .runner import JobRunner

log = logging.getLogger("nepf.worker")
settings = get_settings()
app = make_celery(settings, "nepf-worker")


@app.task(name=TASK_NAME, acks_late=True, reject_on_worker_lost=True, ignore_result=True)
def run_job(job_id: str) -> str:
    """Claim and run one job; the outcome is recorded in the DB (the return value is only a log)."""
    return JobRunner(settings, session_factory(settings.db_url), str(job_id)).run()


@worker_ready.connect
def _reconcile_on_start(**_kw) -> None:
    """A fresh worker re-sends jobs whose worker died (after a crash or broker restart)."""
    try:
        sent = reconcile_once(settings, session_factory(settings.db_url),
                              lambda jid, q: enqueue(app, jid, q))
        if sent:
            log.warning("re-queued %d orphaned job(s) on start", len(sent))
    except Exception as exc:  # noqa: BLE001
        log.warning("reconcile on start failed: %s", exc)
