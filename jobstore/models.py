"""Job store tables (SQLAlchemy 2): the single source of truth for jobs and tokens.

SQLite (default, a file under the data dir, WAL mode) and PostgreSQL (``NEPF_DATABASE_URL``)
are both supported; every state change the worker makes is a single conditional ``UPDATE``
so that it is atomic on both. A change to these classes needs a new Alembic revision in
``jobstore/migrations/versions`` (``tests/test_jobstore_migrations.py`` fails until it exists).
"""

from __future__ import annotations

import datetime as dt
import uuid
from typing import Optional

from sqlalchemy import JSON, Boolean, DateTime, Float, Integer, String, Text, UniqueConstraint
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

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
