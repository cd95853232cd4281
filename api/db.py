"""Job store (SQLAlchemy 2): the single source of truth for jobs and tokens.

SQLite (default, a file under the data dir, WAL mode) and PostgreSQL (``NEPF_DATABASE_URL``)
are both supported; every state change the worker makes is a single conditional ``UPDATE``
so that it is atomic on both.
"""

from __future__ import annotations

import datetime as dt
import threading
import time
import uuid
from typing import Optional

from sqlalchemy import (JSON, Boolean, DateTime, Float, Integer, String, Text, UniqueConstraint,
                        create_engine, event, text)
from sqlalchemy.engine import Engine
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, sessionmaker

STATUSES = ("queued", "running", "succeeded", "failed", "cancelled")
TERMINAL = ("succeeded", "failed", "cancelled")
ACTIVE = ("queued", "running")


def utcnow() -> dt.datetime:
    """Naive UTC (both SQLite and PostgreSQL ``timestamp`` columns store it unchanged)."""
    return dt.datetime.now(dt.timezone.utc).replace(tzinfo=None)


def new_id() -> str:
    return uuid.uuid4().hex


class Base(DeclarativeBase):
    pass


class Token(Base):
    __tablename__ = "nepf_tokens"
    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    owner: Mapped[str] = mapped_column(String(128), index=True)
    name: Mapped[str] = mapped_column(String(128))
    token_hash: Mapped[str] = mapped_column(String(64), unique=True, index=True)
    prefix: Mapped[str] = mapped_column(String(16))
    created_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow)
    revoked: Mapped[bool] = mapped_column(Boolean, default=False)


class Job(Base):
    __tablename__ = "nepf_jobs"
    __table_args__ = (UniqueConstraint("owner", "idempotency_key", name="uq_job_owner_idem"),)

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    owner: Mapped[str] = mapped_column(String(128), index=True)
    name: Mapped[Optional[str]] = mapped_column(String(256), nullable=True)
    status: Mapped[str] = mapped_column(String(16), default="queued", index=True)
    config: Mapped[dict] = mapped_column(JSON, default=dict)
    dataset: Mapped[dict] = mapped_column(JSON, default=dict)   # validator summary
    queue: Mapped[str] = mapped_column(String(32), default="default")
    idempotency_key: Mapped[Optional[str]] = mapped_column(String(256), nullable=True)
    request_hash: Mapped[Optional[str]] = mapped_column(String(64), nullable=True)

    created_at: Mapped[dt.datetime] = mapped_column(DateTime, default=utcnow, index=True)
    started_at: Mapped[Optional[dt.datetime]] = mapped_column(DateTime, nullable=True)
    finished_at: Mapped[Optional[dt.datetime]] = mapped_column(DateTime, nullable=True)
    enqueued_at: Mapped[Optional[dt.datetime]] = mapped_column(DateTime, nullable=True)
    enqueue_count: Mapped[int] = mapped_column(Integer, default=0)

    # progress (written by the worker heartbeat, throttled)
    step: Mapped[int] = mapped_column(Integer, default=0)
    total: Mapped[Optional[int]] = mapped_column(Integer, nullable=True)
    fraction: Mapped[float] = mapped_column(Float, default=0.0)
    stage: Mapped[Optional[str]] = mapped_column(String(64), nullable=True)
    eta_s: Mapped[Optional[float]] = mapped_column(Float, nullable=True)
    wall_s: Mapped[Optional[float]] = mapped_column(Float, nullable=True)

    error: Mapped[Optional[str]] = mapped_column(Text, nullable=True)
    decisions: Mapped[Optional[list]] = mapped_column(JSON, nullable=True)
    result: Mapped[Optional[dict]] = mapped_column(JSON, nullable=True)

    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    # delivery bookkeeping (redelivery cap, lease, exactly-once completion)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    attempt_log: Mapped[list] = mapped_column(JSON, default=list)  # [{"worker","claimed_at","first_step"}]
    lease_owner: Mapped[Optional[str]] = mapped_column(String(128), nullable=True)
    lease_expires: Mapped[Optional[dt.datetime]] = mapped_column(DateTime, nullable=True)
    completions: Mapped[int] = mapped_column(Integer, default=0)


_engines: dict[str, Engine] = {}
_lock = threading.Lock()


def _sqlite_pragmas(dbapi_conn, _record) -> None:
    cur = dbapi_conn.cursor()
    cur.execute("PRAGMA journal_mode=WAL")
    cur.execute("PRAGMA synchronous=NORMAL")
    cur.execute("PRAGMA busy_timeout=30000")
    cur.close()


def get_engine(url: str) -> Engine:
    """One engine per URL per process; creates the tables on first use."""
    with _lock:
        eng = _engines.get(url)
        if eng is not None:
            return eng
        if url.startswith("sqlite"):
            eng = create_engine(url, connect_args={"timeout": 30, "check_same_thread": False},
                                pool_size=20, max_overflow=40)
            event.listen(eng, "connect", _sqlite_pragmas)
        else:
            eng = create_engine(url, pool_size=20, max_overflow=40, pool_pre_ping=True)
        for attempt in range(5):  # two processes creating the schema at once may collide
            try:
                Base.metadata.create_all(eng)
                break
            except Exception:  # noqa: BLE001 - duplicate table/type from a concurrent creator
                if attempt == 4:
                    raise
                time.sleep(0.2 * (attempt + 1))
        _engines[url] = eng
        return eng


def session_factory(url: str) -> sessionmaker:
    return sessionmaker(bind=get_engine(url), expire_on_commit=False)


def dispose_engines() -> None:
    with _lock:
        for eng in _engines.values():
            eng.dispose()
        _engines.clear()


def ping(url: str) -> None:
    with get_engine(url).connect() as conn:
        conn.execute(text("SELECT 1"))
