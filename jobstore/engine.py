"""Engines and sessions of the job store: one engine per URL per process, its schema brought to
the newest Alembic revision on first use (``jobstore.migrate.upgrade``)."""

from __future__ import annotations

import threading

from sqlalchemy import create_engine, event, text
from sqlalchemy.engine import Engine
from sqlalchemy.orm import sessionmaker

from .migrate import upgrade


class _EngineCache:
    """URL -> engine for this process (the pool is per engine, so one engine per URL)."""

    def __init__(self) -> None:
        self.engines: dict[str, Engine] = {}
        self.lock = threading.Lock()


_CACHE = _EngineCache()


def _sqlite_pragmas(dbapi_conn, _record) -> None:
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.execute("PRAGMA busy_timeout=30000")
    cur.close()


def make_engine(url: str) -> Engine:
    """A new engine with the store's pool and SQLite settings (no schema work)."""
    if url.startswith("sqlite"):
        eng = create_engine(url, connect_args={"timeout": 30, "check_same_thread": False},
                            pool_size=20, max_overflow=40)
        event.listen(eng, "connect", _sqlite_pragmas)
        return eng
    return create_engine(url, pool_size=20, max_overflow=40, pool_pre_ping=True)


def get_engine(url: str) -> Engine:
    """This process's engine for ``url``; the first call migrates the schema to head."""
    with _CACHE.lock:
        eng = _CACHE.engines.get(url)
        if eng is None:
            eng = make_engine(url)
            upgrade(eng)
            _CACHE.engines[url] = eng
        return eng


def session_factory(url: str) -> sessionmaker:
    return sessionmaker(bind=get_engine(url), expire_on_commit=False)


def dispose_engines() -> None:
    with _CACHE.lock:
        for eng in _CACHE.engines.values():
            eng.dispose()
        _CACHE.engines.clear()


def ping(url: str) -> None:
    with get_engine(url).connect() as conn:
        conn.execute(text("SELECT 1"))
