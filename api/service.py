"""Per-process service state shared by the routes (settings, DB sessions, auth, broker)."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Optional

from cachetools import TTLCache
from celery import Celery
from fastapi import Request
from sqlalchemy.orm import sessionmaker

from jobstore.engine import session_factory
from jobstore.queue import make_celery, prepare_embedded_broker
from jobstore.storage import Storage, open_storage

from .auth import TokenVerifier, load_secret
from jobstore.settings import Settings


class JobCache:
    """Micro-cache of rendered ``GET /jobs/{id}`` bodies: many pollers of one job cost one DB read
    per ``NEPF_POLL_CACHE_S`` (the worker writes progress about once a second anyway). A bounded
    TTL cache (cachetools; the least recently used entry goes first when full), one lock."""

    MAX_ENTRIES = 5000

    def __init__(self, ttl_s: float) -> None:
        self.ttl_s = ttl_s
        self._d: TTLCache = TTLCache(self.MAX_ENTRIES, ttl=max(ttl_s, 0.0), timer=time.monotonic)
        self._lock = threading.Lock()

    def get(self, job_id: str, owner: str) -> Optional[bytes]:
        with self._lock:
            hit = self._d.get(job_id)
        return hit[1] if hit is not None and hit[0] == owner else None

    def put(self, job_id: str, owner: str, body: bytes) -> None:
        if self.ttl_s <= 0:
            return
        with self._lock:
            self._d[job_id] = (owner, body)

    def drop(self, job_id: str) -> None:
        with self._lock:
            self._d.pop(job_id, None)


@dataclass
class Service:
    settings: Settings
    Session: sessionmaker
    verifier: TokenVerifier
    secret: bytes
    celery: Celery
    storage: Storage = None  # type: ignore[assignment]
    reconciler: Optional[object] = None
    job_cache: "JobCache" = None  # type: ignore[assignment]

    def __post_init__(self) -> None:
        if self.storage is None:
            self.storage = open_storage(self.settings)
        if self.job_cache is None:
            self.job_cache = JobCache(self.settings.poll_cache_s)

    @classmethod
    def create(cls, settings: Settings) -> "Service":
        storage = open_storage(settings)
        check_secret(settings, storage)
        settings.data_path.mkdir(parents=True, exist_ok=True)
        storage.setup()
        settings.uploads_path.mkdir(parents=True, exist_ok=True)
        prepare_embedded_broker(settings)
        Session = session_factory(settings.db_url)
        return cls(settings=settings, Session=Session,
                   verifier=TokenVerifier(Session, settings.auth_cache_s),
                   secret=load_secret(settings.data_path, settings.secret_key),
                   celery=make_celery(settings, "nepf-api"), storage=storage)


class StartupError(RuntimeError):
    """A setting that makes the service unusable; ``nepf serve`` prints it and exits 2."""


def check_secret(settings: Settings, storage: Storage) -> None:
    """When the job files are reachable from several machines, API processes may run on several:
    a per-machine ``secret.key`` would make each refuse the others' SSE tickets, so the key must be
    given (``NEPF_SECRET_KEY``)."""
    if storage.multi_machine and not settings.secret_key:
        raise StartupError("NEPF_STORAGE_URL is set but NEPF_SECRET_KEY is not: every API process must sign "
                           "SSE tickets with the same key (e.g. NEPF_SECRET_KEY=$(python -c 'import secrets; "
                           "print(secrets.token_urlsafe(32))'))")


async def get_service(request: Request) -> Service:
    # async: a sync dependency would cost a thread-pool hop on every request
    return request.app.state.service
