"""Bearer tokens (stored as SHA-256 hashes) and short-lived signed SSE tickets.

Tokens are 256-bit random strings, so a fast unsalted hash is enough: there is nothing to
brute-force, and the DB never holds a usable token. A verified token is cached in the API
process for ``NEPF_AUTH_CACHE_S`` seconds (revocation takes effect after at most that long).
An SSE ticket names the token it was minted with, and opening a stream checks, uncached, that
the token is still live: a revoked token's tickets stop working at once.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
import os
import secrets
import threading
import time
from pathlib import Path
from typing import Optional

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
    """Token -> owner, with a small TTL cache (the hot path of 200 pollers)."""

    def __init__(self, Session: sessionmaker, ttl_s: float) -> None:
        self.Session = Session
        self.ttl_s = ttl_s
        self._cache: dict[str, tuple[float, Optional[str]]] = {}
        self._lock = threading.Lock()

    def cached(self, token: str) -> tuple[bool, Optional[str]]:
        """``(hit, owner)`` from the cache only (no I/O)."""
        if not token or len(token) > 512:
            return True, None
        hit = self._cache.get(hash_token(token))
        if hit is not None and hit[0] > time.monotonic():
            return True, hit[1]
        return False, None

    def owner_of(self, token: str) -> Optional[str]:
        if not token or len(token) > 512:
            return None
        h = hash_token(token)
        now = time.monotonic()
        with self._lock:
            hit = self._cache.get(h)
            if hit is not None and hit[0] > now:
                return hit[1]
        with self.Session() as s:
            row = s.execute(select(Token.owner).where(Token.token_hash == h, Token.revoked.is_(False))).first()
        owner = row[0] if row else None
        with self._lock:
            if len(self._cache) > 10000:
                self._cache.clear()
            self._cache[h] = (now + (self.ttl_s if owner else 1.0), owner)
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


def _b64(b: bytes) -> str:
    return base64.urlsafe_b64encode(b).rstrip(b"=").decode("ascii")


def _unb64(s: str) -> bytes:
    return base64.urlsafe_b64decode(s + "=" * (-len(s) % 4))


def make_ticket(secret: bytes, owner: str, job_id: str, ttl_s: int, token_id: int) -> str:
    """A signed ``{owner, job, exp, token}``: good for one job's event stream, for ``ttl_s``
    seconds, and only while the bearer token it was minted with (row ``token_id``) is not revoked."""
    body = _b64(json.dumps({"o": owner, "j": job_id, "e": int(time.time()) + int(ttl_s), "k": int(token_id)},
                           separators=(",", ":")).encode())
    sig = _b64(hmac.new(secret, body.encode(), hashlib.sha256).digest())
    return f"{body}.{sig}"


def check_ticket(secret: bytes, ticket: str, job_id: str) -> Optional[tuple[str, int]]:
    """``(owner, token_id)`` of a valid, unexpired ticket for ``job_id``; otherwise None. Whether
    the token is still live is the caller's check (:meth:`TokenVerifier.token_is_live`): it needs
    the DB. A ticket without a token id (minted before tickets carried one) is invalid."""
    try:
        body, sig = ticket.split(".", 1)
        want = _b64(hmac.new(secret, body.encode(), hashlib.sha256).digest())
        if not hmac.compare_digest(want, sig):
            return None
        data = json.loads(_unb64(body))
        if data.get("j") != job_id or int(data.get("e", 0)) < time.time():
            return None
        owner, token_id = data.get("o"), data.get("k")
        if not isinstance(owner, str) or not isinstance(token_id, int) or isinstance(token_id, bool):
            return None
        return owner, token_id
    except Exception:  # noqa: BLE001 - any malformed ticket is just invalid
        return None
