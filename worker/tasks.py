"""The Celery app of the worker and its one task, ``nepf.run_job`` (sent by name by the API)."""

from __future__ import annotations

import logging
import signal
import threading

from celery.signals import worker_ready, worker_shutdown, worker_shutting_down

from jobstore.settings import get_settings
from jobstore.engine import session_factory
from jobstore.queue import TASK_NAME, enqueue, make_celery
from jobstore.reconcile import reconcile_once

from .health import Heartbeat
from .runner import JobRunner

log = logging.getLogger("nepf.worker")
settings = get_settings()
app = make_celery(settings, "nepf-worker")
#: set once this worker starts shutting down: the running job stops at its next step and goes back
#: to the queue (``JobRunner.requeue``) instead of ending failed or cancelled
shutting_down = threading.Event()


@app.task(name=TASK_NAME, acks_late=True, reject_on_worker_lost=True, ignore_result=True)
def run_job(job_id: str) -> str:
    """Claim and run one job; the outcome is recorded in the DB (the return value is only a log)."""
    return JobRunner(settings, session_factory(settings.db_url), str(job_id), shutdown=shutting_down).run()


@worker_shutting_down.connect
def _on_shutting_down(**_kw) -> None:
    """SIGTERM / SIGINT (Celery's warm shutdown, also what a dying ``nepf serve`` sends)."""
    shutting_down.set()


@worker_ready.connect
def _flag_cold_shutdown(**_kw) -> None:
    """SIGQUIT (cold shutdown): Celery cancels the running task by raising into it before it
    announces the shutdown, so set the flag first; the runner then re-queues the job."""
    previous = signal.getsignal(signal.SIGQUIT)
    if not callable(previous):
        return

    def flag_then_celery(signum, frame):
        shutting_down.set()
        previous(signum, frame)
    try:
        signal.signal(signal.SIGQUIT, flag_then_celery)
    except ValueError:   # not the main thread: the warm-shutdown flag still works
        pass


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


@worker_ready.connect
def _start_heartbeat(**_kw) -> None:
    """The liveness file that ``nepf worker --check`` reads (worker/health.py)."""
    beat = Heartbeat()
    beat.start()
    worker_shutdown.connect(lambda **_: beat.stop(), weak=False)
