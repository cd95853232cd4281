"""Celery configuration shared by the API (sender) and the worker (consumer).

The API enqueues by task *name* (``send_task("nepf.run_job")``) and never imports the task
code, so it never imports torch or ``nepf_core``.

Embedded default (no ``NEPF_BROKER_URL``): the broker is kombu's SQLAlchemy transport on a
SQLite file in the data dir (``DATA_DIR/broker.sqlite3``), registered here as the
``nepfsqla`` transport so that its polling interval can be set (kombu passes every
transport option of the stock ``sqla`` transport to ``create_engine``). Messages that a
crashed worker had taken are not redelivered by this transport; the reconciler
(``jobstore/reconcile.py``) re-queues them from the job store, which is the source of truth.
"""

from __future__ import annotations

import fcntl

from celery import Celery
from kombu import Queue
from kombu.transport import TRANSPORT_ALIASES
from kombu.transport import sqlalchemy as _kombu_sqla

from .settings import Settings

TASK_NAME = "nepf.run_job"
QUEUES = ("default", "gpu")


class EmbeddedTransport(_kombu_sqla.Transport):
    """kombu SQLAlchemy transport with a configurable polling interval."""

    polling_interval = 0.1


TRANSPORT_ALIASES.setdefault("nepfsqla", "jobstore.queue:EmbeddedTransport")


def celery_config(settings: Settings) -> dict:
    url = settings.effective_broker_url
    if settings.embedded:
        EmbeddedTransport.polling_interval = settings.embedded_poll_s
        # the stock transport passes its options to create_engine: wait for the SQLite lock
        transport_options: dict = {"connect_args": {"timeout": 30}}
    else:
        transport_options = {"visibility_timeout": settings.visibility_timeout_s}
    return dict(
        broker_url=url,
        broker_transport_options=transport_options,
        broker_connection_retry_on_startup=True,
        broker_connection_max_retries=None,   # keep reconnecting across a broker restart
        task_default_queue="default",
        task_queues=[Queue(q, routing_key=q) for q in QUEUES],
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        task_ignore_result=True,              # progress lives in our DB, not a result backend
        worker_prefetch_multiplier=1,
        worker_send_task_events=False,
        worker_hijack_root_logger=False,
        task_serializer="json",
        accept_content=["json"],
        broker_pool_limit=4,
    )


def make_celery(settings: Settings, name: str = "nepf") -> Celery:
    app = Celery(name)
    app.conf.update(celery_config(settings))
    return app


def declare_queues(app: Celery) -> None:
    """Declare every queue of ``app`` on its broker (what a sender's or consumer's first use does)."""
    with app.connection_for_write() as conn:
        channel = conn.channel()
        try:
            for queue in app.conf.task_queues:
                queue(channel).declare()
        finally:
            channel.close()


def prepare_embedded_broker(settings: Settings) -> None:
    """Create the embedded broker's tables and queue rows, one process at a time.

    kombu's SQLAlchemy transport creates its tables (``create_all``: look, then ``CREATE``) and
    each queue's row on first use in every process. ``nepf serve`` and its worker start together
    on a fresh data dir, and the loser of that race gets "table kombu_queue already exists" or
    "UNIQUE constraint failed: kombu_queue.name": the worker died at its start, or an upload
    failed. Declaring every queue here under an ``flock`` on ``broker.sqlite3.prepare-lock``
    leaves nothing for the first use to create. Both entry points call it before they touch the
    broker (the API's ``Service.create``, the worker's ``worker_main``); a no-op on an external broker.
    """
    if not settings.embedded:
        return
    db = settings.embedded_broker_path
    db.parent.mkdir(parents=True, exist_ok=True)
    with open(f"{db}.prepare-lock", "a") as lock:       # closing it releases the flock
        fcntl.flock(lock, fcntl.LOCK_EX)
        declare_queues(make_celery(settings, "nepf-prepare"))


def enqueue(app: Celery, job_id: str, queue: str) -> None:
    """Send one job message by task name (the payload is only the job id; the DB has the rest)."""
    app.send_task(TASK_NAME, args=[job_id], queue=queue, routing_key=queue,
                  retry=True, retry_policy={"max_retries": 3, "interval_start": 0.2,
                                            "interval_step": 0.5, "interval_max": 2})


MIN_REDIS = (6, 2)


def check_redis_version(version: str) -> None:
    """Kombu's Redis transport needs Redis >= 6.2 (the PyPI ``redis-server`` 6.0.9 crashes workers)."""
    parts = tuple(int(x) for x in version.split(".")[:2] if x.isdigit())
    if parts < MIN_REDIS:
        raise RuntimeError(f"Redis {version} is too old: NePF's Celery transport needs Redis >= 6.2")


def ping_broker(app: Celery, timeout: float = 2.0) -> None:
    with app.connection_for_write() as conn:
        conn.ensure_connection(max_retries=1, timeout=timeout)
        if conn.transport_cls in ("redis", "rediss"):
            client = conn.default_channel.client
            check_redis_version(str(client.info("server").get("redis_version", "0")))
            return
        if not app.conf.broker_url.startswith("nepfsqla"):
            return
        # the SQLite broker "connects" lazily; touch the file for real
        chan = conn.default_channel
        chan.session.execute(_kombu_sqla.text("SELECT 1"))
