"""API keys: creation, storage as a hash, and constant-time verification.

A key reads ``nw_<prefix>_<secret>``: the prefix finds the stored row, the SHA-256 of the
whole key is compared in constant time. Keys carry 256 random bits, so a slow password hash
would add nothing but latency to every request.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from dataclasses import dataclass
from enum import IntEnum

from sqlalchemy import select
from sqlalchemy.orm import Session

from service.tables import ApiKey, Organisation

KEY_PREFIX = "nw"


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


def create_key(session: Session, organisation_name: str, role: Role) -> str:
    """Create a key (and its organisation if new); the key is returned once and never stored."""
    organisation = session.scalar(select(Organisation).where(Organisation.name == organisation_name))
    if organisation is None:
        organisation = Organisation(name=organisation_name)
        session.add(organisation)
        session.flush()
    prefix = secrets.token_hex(6)
    key = f"{KEY_PREFIX}_{prefix}_{secrets.token_urlsafe(32)}"
    session.add(
        ApiKey(organisation_id=organisation.id, prefix=prefix, key_hash=hash_key(key), role=role.name)
    )
    return key


def authenticate(session: Session, key: str) -> Principal | None:
    """The principal a key belongs to, or None for a malformed, unknown or revoked key."""
    parts = key.split("_", 2)
    if len(parts) != 3 or parts[0] != KEY_PREFIX:
        return None
    row = session.scalar(select(ApiKey).where(ApiKey.prefix == parts[1]))
    if row is None or row.revoked_at is not None:
        return None
    if not hmac.compare_digest(row.key_hash, hash_key(key)):
        return None
    return Principal(row.organisation_id, Role[row.role], row.id)
