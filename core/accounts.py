"""Users, their API tokens and signed URLs: the parts of access control that need no web framework, shared
by the API and the ``fotoskhema users`` command.

A token is ``fsk_`` + 43 URL-safe random characters (256 bits). Only its SHA-256 is stored: a stolen database
gives no usable token, and a random 256-bit secret needs no slow password hash. A signed URL carries
``exp`` (Unix seconds) and ``sig``, an HMAC-SHA256 over the job it opens and ``exp`` with the service's secret
key: image tags and ``EventSource`` cannot send an ``Authorization`` header, so tiles, downloads and the event
stream of one job may be read with such a URL until it expires.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import re
import secrets
import threading
import time
from dataclasses import dataclass
from datetime import datetime, timedelta
from functools import lru_cache
from pathlib import Path

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from core.db import ApiToken, Database, User, utcnow

TOKEN_PREFIX = "fsk_"
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
LAST_USED_RESOLUTION = timedelta(minutes=1)  # ``last_used_at`` is written at most this often per token
SIGNED_URL_STEP = 3600  # expiry times are rounded up to this, so a job's signed URLs stay the same a while


class AccountError(ValueError):
    """A request about users or tokens that cannot be done (unknown user, duplicate name, bad name)."""


@dataclass(frozen=True)
class Principal:
    """Who a request acts for."""

    user_id: int
    name: str
    is_admin: bool

    def may_see(self, owner_id: int | None) -> bool:
        """Admins see everything; others what they made (records from before accounts have no owner)."""
        return self.is_admin or (owner_id is not None and owner_id == self.user_id)


@dataclass(frozen=True)
class TokenInfo:
    id: int
    user: str
    prefix: str
    label: str
    created_at: datetime
    last_used_at: datetime | None
    revoked: bool


def hash_token(token: str) -> str:
    return hashlib.sha256(token.encode("utf-8", "replace")).hexdigest()


def create_user(db: Database, name: str, *, admin: bool = False, label: str = "") -> str:
    """Make user ``name`` with a first token; returns that token (shown once, stored only as a hash)."""
    if not NAME_PATTERN.fullmatch(name):
        raise AccountError(f"user name {name[:80]!r}: use 1-64 letters, digits, '.', '_' or '-'")
    with db.session() as s:
        if s.scalar(select(User).where(User.name == name)) is not None:
            raise AccountError(f"user {name!r} already exists")
        user = User(name=name, is_admin=admin)
        s.add(user)
        s.flush()
        return _new_token(user, label)


def issue_token(db: Database, name: str, *, label: str = "") -> str:
    """A new token for user ``name`` (their other tokens stay valid)."""
    with db.session() as s:
        return _new_token(_user(s, name), label)


def _new_token(user: User, label: str) -> str:
    token = TOKEN_PREFIX + secrets.token_urlsafe(32)
    user.tokens.append(ApiToken(token_hash=hash_token(token), prefix=token[:10], label=label[:200]))
    return token


def revoke_token(db: Database, token_id: int, *, by: Principal | None = None) -> TokenInfo:
    """Revoke one token by its id; ``by`` (when given) must own it or be an admin."""
    with db.session() as s:
        token = s.get(ApiToken, token_id)
        if token is None or (by is not None and not by.may_see(token.user_id)):
            raise AccountError(f"no token {token_id}")
        if token.revoked_at is None:
            token.revoked_at = utcnow()
        return _info(token)


def revoke_user_tokens(db: Database, name: str) -> int:
    """Revoke every token of user ``name``; returns how many were still valid."""
    with db.session() as s:
        live = [t for t in _user(s, name).tokens if t.revoked_at is None]
        for token in live:
            token.revoked_at = utcnow()
        return len(live)


def list_users(db: Database, user_id: int | None = None) -> list[tuple[str, bool, list[TokenInfo]]]:
    """Every user (or the one ``user_id``) with their tokens."""
    query = select(User).order_by(User.id)
    if user_id is not None:
        query = query.where(User.id == user_id)
    with db.session() as s:
        return [(u.name, u.is_admin, [_info(t) for t in u.tokens]) for u in s.scalars(query)]


def has_users(db: Database) -> bool:
    with db.session() as s:
        return s.scalar(select(User.id).limit(1)) is not None


def authenticate(db: Database, token: str) -> Principal | None:
    """The user an unrevoked token belongs to, or None (one query; ``last_used_at`` written once a minute)."""
    if not token.startswith(TOKEN_PREFIX) or len(token) > 200:
        return None
    digest = hash_token(token)
    with db.session() as s:
        row = s.execute(
            select(ApiToken.id, ApiToken.last_used_at, User.id, User.name, User.is_admin)
            .join(User, ApiToken.user_id == User.id)
            .where(ApiToken.token_hash == digest, ApiToken.revoked_at.is_(None))
        ).first()
        if row is None:
            return None
        token_id, last_used, user_id, name, is_admin = row
        now = utcnow()
        if last_used is None or now - last_used > LAST_USED_RESOLUTION:
            s.execute(update(ApiToken).where(ApiToken.id == token_id).values(last_used_at=now))
        return Principal(user_id, name, is_admin)


class TokenCache:
    """``authenticate`` remembered for ``ttl`` seconds per token, so a map's tile requests do not each query
    the database. Revoking in this process clears it; another process's revocation takes effect here within
    ``ttl``."""

    def __init__(self, db: Database, ttl: float = 5.0, size: int = 1024) -> None:
        self.db, self.ttl, self.size = db, ttl, size
        self._known: dict[str, tuple[float, Principal]] = {}
        self._lock = threading.Lock()

    def authenticate(self, token: str) -> Principal | None:
        now = time.monotonic()
        with self._lock:
            hit = self._known.get(token)
        if hit is not None and now - hit[0] < self.ttl:
            return hit[1]
        principal = authenticate(self.db, token)
        with self._lock:
            if principal is None:
                self._known.pop(token, None)
            else:
                if len(self._known) >= self.size:
                    self._known.clear()
                self._known[token] = (now, principal)
        return principal

    def clear(self) -> None:
        with self._lock:
            self._known.clear()


def _user(session: Session, name: str) -> User:
    user = session.scalar(select(User).where(User.name == name))
    if user is None:
        raise AccountError(f"no user {name[:80]!r}")
    return user


def _info(token: ApiToken) -> TokenInfo:
    return TokenInfo(
        token.id,
        token.user.name,
        token.prefix,
        token.label,
        token.created_at,
        token.last_used_at,
        token.revoked_at is not None,
    )


# -- Signed URLs ---------------------------------------------------------------------------------


@lru_cache(maxsize=16)
def signing_key(secret: str, data_dir: Path) -> bytes:
    """``secret`` if set, else the random key in ``<data_dir>/secret_key``, made (0600) on first use, so every
    API process on one data dir signs alike. Read once per process: every signed tile request asks for it."""
    if secret:
        return secret.encode()
    path = data_dir / "secret_key"
    if not path.exists():
        data_dir.mkdir(parents=True, exist_ok=True)
        temp = data_dir / f".secret_key.{os.getpid()}"
        fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as out:
            out.write(secrets.token_hex(32))
        try:
            os.link(temp, path)  # never replaces a key another process wrote meanwhile
        except FileExistsError:
            pass
        finally:
            temp.unlink(missing_ok=True)
    return path.read_text().strip().encode()


def job_scope(job_id: int, created_at: datetime) -> str:
    """What a job's signed URLs open: the job, told apart from a later one that reuses its id."""
    return f"job:{job_id}:{created_at.timestamp():.6f}"


def flight_scope(flight_id: int, created_at: datetime) -> str:
    """What a flight's signed URLs open (its photos' previews), told apart from a later flight with its id."""
    return f"flight:{flight_id}:{created_at.timestamp():.6f}"


def sign(key: bytes, scope: str, valid_seconds: int, now: float | None = None) -> dict[str, str]:
    """Query parameters ``exp`` and ``sig`` that open ``scope`` for at least ``valid_seconds``."""
    now = time.time() if now is None else now
    exp = (int(now + valid_seconds) // SIGNED_URL_STEP + 1) * SIGNED_URL_STEP
    return {"exp": str(exp), "sig": _mac(key, scope, exp)}


def signature_valid(key: bytes, scope: str, exp: str, sig: str, now: float | None = None) -> bool:
    if not (exp.isascii() and exp.isdigit()) or len(exp) > 12 or not sig.isascii() or len(sig) > 128:
        return False
    now = time.time() if now is None else now
    return int(exp) > now and hmac.compare_digest(_mac(key, scope, int(exp)), sig)


def _mac(key: bytes, scope: str, exp: int) -> str:
    return hmac.new(key, f"{scope}\n{exp}".encode(), hashlib.sha256).hexdigest()[:43]
