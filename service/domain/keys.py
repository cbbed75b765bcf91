"""API keys, listed, created and revoked: by an organisation's admins over the API (their own
organisation's only) and by the operator on the command line (every organisation's)."""

from __future__ import annotations

import datetime as dt

from sqlalchemy import select
from sqlalchemy.orm import Session, joinedload

from service.domain.errors import NotFoundError
from service.domain.logins import end_logins
from service.security import PREFIX_LENGTH, Principal, Role, issue_key
from service.tables import MAX_ID, ApiKey, utcnow


def list_keys(session: Session, organisation_id: int | None = None) -> list[ApiKey]:
    """The keys of one organisation, or of all (the command line), oldest first."""
    query = select(ApiKey).options(joinedload(ApiKey.organisation)).order_by(ApiKey.id)
    if organisation_id is not None:
        query = query.where(ApiKey.organisation_id == organisation_id)
    return list(session.scalars(query))


def create_key(
    session: Session, principal: Principal, role: Role, expires_at: dt.datetime | None
) -> tuple[ApiKey, str]:
    """A new key of the caller's organisation, and the key itself (shown once). Only admins,
    the highest role, create keys, so its role is never above the caller's."""
    return issue_key(session, principal.organisation_id, role, expires_at)


def get_key(session: Session, principal: Principal, key_id: int) -> ApiKey:
    """One of the caller's organisation's keys; another organisation's is as unknown as a missing one."""
    key = session.get(ApiKey, key_id)
    if key is None or key.organisation_id != principal.organisation_id:
        raise NotFoundError("API key", key_id)
    return key


def find_key(session: Session, reference: str) -> ApiKey:
    """The key whose id or prefix is ``reference`` (prefixes are longer than any id)."""
    if reference.isdigit() and len(reference) < PREFIX_LENGTH:
        key = session.get(ApiKey, int(reference)) if int(reference) <= MAX_ID else None
    else:
        key = session.scalar(select(ApiKey).where(ApiKey.prefix == reference))
    if key is None:
        raise NotFoundError("API key", reference)
    return key


def revoke_key(session: Session, key: ApiKey) -> ApiKey:
    """Revoke a key and end the dashboard logins opened with it; revoking twice keeps the first time."""
    if key.revoked_at is None:
        key.revoked_at = utcnow()
    end_logins(session, key.id)
    session.flush()
    return key
