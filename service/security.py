"""API keys: creation, storage as a hash, and constant-time verification.

A key reads ``nw_<prefix>_<secret>``: the prefix finds the stored row, the SHA-256 of the
whole key is compared in constant time. Keys carry 256 random bits, so a slow password hash
would add nothing but latency to every request. A key ends when it is revoked or expires; its
last use is recorded to the minute.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import hmac
import secrets
from dataclasses import dataclass
from enum import IntEnum

from sqlalchemy import bindparam, or_, select, update
from sqlalchemy.orm import Session

from models.errors import InputError
from recordfiles.names import normalised_name
from service.tables import ApiKey, Organisation, utcnow

KEY_PREFIX = "nw"
PREFIX_BYTES = 6
PREFIX_LENGTH = 2 * PREFIX_BYTES  # hexadecimal digits
# How stale a key's recorded last use may be: recording it costs a write only this often.
USE_RECORDED_EVERY = dt.timedelta(minutes=1)
NOT_VALID = "the API key is not valid (unknown, malformed or revoked)"
# Built once: every request authenticates.
KEY_OF_PREFIX = select(ApiKey).where(ApiKey.prefix == bindparam("prefix"))


class Role(IntEnum):
    """Roles in increasing power: each can do what the ones below it can."""

    viewer = 1
    ingest = 2
    admin = 3


@dataclass(frozen=True)
class Principal:
    """Who is calling: their organisation and role."""

    organisation_id: int
    role: Role
    key_id: int


def hash_key(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()


class KeyRefusedError(Exception):
    """A key that authenticates no one; the message says why, as far as is safe to say: only
    the holder of the whole key learns that it expired."""


def create_key(
    session: Session, organisation_name: str, role: Role, expires_at: dt.datetime | None = None
) -> str:
    """Create a key (and its organisation if new, its name normalised: ``recordfiles.names``); the
    key is returned once and never stored."""
    organisation_name = normalised_name(organisation_name, "organisation name")
    organisation = session.scalar(select(Organisation).where(Organisation.name == organisation_name))
    if organisation is None:
        organisation = Organisation(name=organisation_name)
        session.add(organisation)
        session.flush()
    return issue_key(session, organisation.id, role, expires_at)[1]


def issue_key(
    session: Session, organisation_id: int, role: Role, expires_at: dt.datetime | None
) -> tuple[ApiKey, str]:
    """A new key of an existing organisation: its stored row (flushed) and the key itself."""
    if expires_at is not None and expires_at <= utcnow():
        raise InputError(f"the expiry {expires_at.isoformat()} has passed; give a time in the future")
    prefix = secrets.token_hex(PREFIX_BYTES)
    key = f"{KEY_PREFIX}_{prefix}_{secrets.token_urlsafe(32)}"
    row = ApiKey(
        organisation_id=organisation_id,
        prefix=prefix,
        key_hash=hash_key(key),
        role=role.name,
        expires_at=expires_at,
    )
    session.add(row)
    session.flush()
    return row, key


def authenticate(session: Session, key: str) -> Principal:
    """The principal a key belongs to; ``KeyRefusedError`` for a malformed, unknown, revoked or
    expired key. Records the key's use when the recorded one is a minute old or more."""
    parts = key.split("_", 2)
    if len(parts) != 3 or parts[0] != KEY_PREFIX:
        raise KeyRefusedError(NOT_VALID)
    row = session.scalar(KEY_OF_PREFIX, {"prefix": parts[1]})
    if row is None or row.revoked_at is not None or not hmac.compare_digest(row.key_hash, hash_key(key)):
        raise KeyRefusedError(NOT_VALID)
    now = utcnow()
    if has_expired(row, now):
        raise KeyRefusedError(
            f"the API key expired at {row.expires_at:%Y-%m-%d %H:%M:%S} UTC; ask an admin for a new one"
        )
    if row.last_used_at is None or now - row.last_used_at >= USE_RECORDED_EVERY:
        _record_use(session, row.id, now)
    return principal_of(row)


def has_expired(key: ApiKey, now: dt.datetime) -> bool:
    """Whether a key's lifetime has ended (a key without expiry lasts until revoked)."""
    return key.expires_at is not None and key.expires_at <= now


def principal_of(key: ApiKey) -> Principal:
    return Principal(key.organisation_id, Role[key.role], key.id)


def _record_use(session: Session, key_id: int, now: dt.datetime) -> None:
    """Set the key's last use in a transaction of its own, committed at once: the request's own
    may run long or be rolled back. The compare on the old value lets one of several requests
    arriving together write it."""
    stale = now - USE_RECORDED_EVERY
    with Session(session.get_bind()) as own:
        own.execute(
            update(ApiKey)
            .where(ApiKey.id == key_id, or_(ApiKey.last_used_at.is_(None), ApiKey.last_used_at <= stale))
            .values(last_used_at=now)
        )
        own.commit()
