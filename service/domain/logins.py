"""Dashboard logins: an API key exchanged for a random session token held in a cookie.

The browser never keeps the API key: it keeps a 256-bit token whose SHA-256 is stored with
the key it was opened with. A login ends at logout, at expiry, or when its key expires or is
revoked.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import secrets
from dataclasses import dataclass

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from service.security import KeyRefusedError, Principal, Role, authenticate, has_expired, principal_of
from service.tables import ApiKey, DashboardSession, Organisation, utcnow


@dataclass(frozen=True)
class Login:
    """Who is looking at the dashboard."""

    principal: Principal
    organisation: str


def open_login(session: Session, key: str, lifetime: dt.timedelta) -> str | None:
    """A new session token for a valid key of role viewer or higher; None for any other key."""
    try:
        principal = authenticate(session, key.strip())
    except KeyRefusedError:
        return None
    if principal.role < Role.viewer:
        return None
    token = secrets.token_urlsafe(32)
    now = utcnow()
    session.execute(delete(DashboardSession).where(DashboardSession.expires_at <= now))
    session.add(
        DashboardSession(token_hash=_hash(token), api_key_id=principal.key_id, expires_at=now + lifetime)
    )
    return token


def find_login(session: Session, token: str) -> Login | None:
    """The login a token stands for, unless it or its key expired, or its key was revoked."""
    row = session.execute(
        select(ApiKey, Organisation.name)
        .join(DashboardSession, DashboardSession.api_key_id == ApiKey.id)
        .join(Organisation, Organisation.id == ApiKey.organisation_id)
        .where(DashboardSession.token_hash == _hash(token), DashboardSession.expires_at > utcnow())
    ).one_or_none()
    if row is None or row.ApiKey.revoked_at is not None or has_expired(row.ApiKey, utcnow()):
        return None
    return Login(principal_of(row.ApiKey), row.name)


def close_login(session: Session, token: str) -> None:
    """End a login (an unknown token is already ended)."""
    session.execute(delete(DashboardSession).where(DashboardSession.token_hash == _hash(token)))


def end_logins(session: Session, key_id: int) -> None:
    """End every login opened with a key (it is being revoked)."""
    session.execute(delete(DashboardSession).where(DashboardSession.api_key_id == key_id))


def _hash(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()
