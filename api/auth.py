"""Bearer tokens (stored as SHA-256 hashes) and short-lived signed SSE tickets (itsdangerous).

Tokens are 256-bit random strings, so a fast unsalted hash is enough: there is nothing to
brute-force, and the DB never holds a usable token. A verified token is cached in the API
process for ``NEPF_AUTH_CACHE_S`` seconds (revocation takes effect after at most that long).
An SSE ticket names the token it was minted with, and opening a stream checks, uncached, that
the token is still live: a revoked token's tickets stop working at once.
"""

from __future__ import annotations

import hashlib
import os
import secrets
import threading
import time
from pathlib import Path
from typing import Optional

from cachetools import TTLCache
from itsdangerous import BadData, URLSafeTimedSerializer
from sqlalchemy import select
from sqlalchemy.orm import sessionmaker

from jobstore.models import Token

TOKEN_PREFIX = "nepf_"


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


def create_token(Session: sessionmaker, owner: str, name: Optional[str] = None) -> str:
    """Create a token for ``owner`` and return it in clear (the only time it is visible)."""
    token = TOKEN_PREFIX + secrets.token_urlsafe(32)
    with Session() as s:
        s.add(Token(owner=owner, name=name or owner, token_hash=hash_token(token), prefix=token[:12]))
        s.commit()
    return token


class TokenVerifier:
    """Token -> owner, with TTL caches (the hot path of 200 pollers): a live token's owner for
    ``ttl_s`` (so a revocation takes effect after at most that long), an unknown token for 1 s.
    Both are bounded LRU-with-expiry caches (cachetools), guarded by one lock."""

    MAX_ENTRIES = 10_000
    MISS_TTL_S = 1.0

    def __init__(self, Session: sessionmaker, ttl_s: float) -> None:
        self.Session = Session
        self.ttl_s = ttl_s
        self._owners: TTLCache = TTLCache(self.MAX_ENTRIES, ttl=ttl_s, timer=time.monotonic)
        self._misses: TTLCache = TTLCache(self.MAX_ENTRIES, ttl=self.MISS_TTL_S, timer=time.monotonic)
        self._lock = threading.Lock()

    def _lookup(self, h: str) -> tuple[bool, Optional[str]]:
        with self._lock:
            owner = self._owners.get(h)
            if owner is not None:
                return True, owner
            return h in self._misses, None

    def cached(self, token: str) -> tuple[bool, Optional[str]]:
        """``(hit, owner)`` from the cache only (no I/O)."""
        if not token or len(token) > 512:
            return True, None
        return self._lookup(hash_token(token))

    def owner_of(self, token: str) -> Optional[str]:
        if not token or len(token) > 512:
            return None
        h = hash_token(token)
        hit, owner = self._lookup(h)
        if hit:
            return owner
        with self.Session() as s:
            row = s.execute(select(Token.owner).where(Token.token_hash == h, Token.revoked.is_(False))).first()
        owner = row[0] if row else None
        with self._lock:
            if owner is not None:
                self._owners[h] = owner
            else:
                self._misses[h] = True
        return owner

    def token_id(self, token: str) -> Optional[int]:
        """The row id of a live token (what a ticket names), or None. Uncached: minting a ticket
        is rare, and the id must belong to this very token."""
        if not token or len(token) > 512:
            return None
        with self.Session() as s:
            row = s.execute(select(Token.id).where(Token.token_hash == hash_token(token),
                                                   Token.revoked.is_(False))).first()
        return row[0] if row else None

    def token_is_live(self, token_id: int, owner: str) -> bool:
        """True while token ``token_id`` of ``owner`` exists and is not revoked. Uncached: an SSE
        connect is rare, and a revoked token's tickets must stop at once (issue 37)."""
        with self.Session() as s:
            return s.execute(select(Token.id).where(Token.id == token_id, Token.owner == owner,
                                                    Token.revoked.is_(False))).first() is not None


def load_secret(data_dir: Path, configured: Optional[str]) -> bytes:
    """HMAC key: ``NEPF_SECRET_KEY`` or a random key kept (0600) in the data dir."""
    if configured:
        return configured.encode("utf-8")
    path = Path(data_dir) / "secret.key"
    try:
        return path.read_bytes()
    except FileNotFoundError:
        pass
    key = secrets.token_bytes(32)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".tmp{os.getpid()}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(key)
    try:
        os.link(tmp, path)          # first writer wins (several API processes)
    except FileExistsError:
        pass
    finally:
        tmp.unlink(missing_ok=True)
    return path.read_bytes()


TICKET_SALT = "nepf.sse-ticket"


def _ticket_serializer(secret: bytes) -> URLSafeTimedSerializer:
    return URLSafeTimedSerializer(secret, salt=TICKET_SALT, signer_kwargs={"digest_method": hashlib.sha256})


def make_ticket(secret: bytes, owner: str, job_id: str, token_id: int) -> str:
    """A signed, timestamped ``{owner, job, token}`` (itsdangerous): good for one job's event
    stream, for ``NEPF_TICKET_TTL_S`` from now (checked when it is used), and only while the
    bearer token it was minted with (row ``token_id``) is not revoked."""
    return _ticket_serializer(secret).dumps({"o": owner, "j": job_id, "k": int(token_id)})


def check_ticket(secret: bytes, ticket: str, job_id: str, max_age_s: float) -> Optional[tuple[str, int]]:
    """``(owner, token_id)`` of a ticket for ``job_id`` signed with ``secret`` at most
    ``max_age_s`` ago; otherwise None. Whether the token is still live is the caller's check
    (:meth:`TokenVerifier.token_is_live`): it needs the DB."""
    try:
        data = _ticket_serializer(secret).loads(ticket, max_age=max_age_s)
    except BadData:   # bad signature, expired, malformed
        return None
    if not isinstance(data, dict) or data.get("j") != job_id:
        return None
    owner, token_id = data.get("o"), data.get("k")
    if not isinstance(owner, str) or not isinstance(token_id, int) or isinstance(token_id, bool):
        return None
    return owner, token_id
