"""An organisation's API keys, for its admins: listed, created and revoked."""

from __future__ import annotations

from fastapi import APIRouter, status

from service.api.deps import Admin, SessionDep
from service.api.params import IdPath
from service.domain import keys
from service.schemas import KeyCreate, KeyCreated, KeyOut
from service.security import Role
from service.tables import ApiKey

router = APIRouter(prefix="/keys", tags=["keys"])


def key_out(key: ApiKey) -> KeyOut:
    return KeyOut.model_validate(key, from_attributes=True)


@router.get("")
def list_keys(principal: Admin, session: SessionDep) -> list[KeyOut]:
    """Your organisation's keys, revoked and expired ones included."""
    return [key_out(key) for key in keys.list_keys(session, principal.organisation_id)]


@router.post("", status_code=status.HTTP_201_CREATED)
def create_key(body: KeyCreate, principal: Admin, session: SessionDep) -> KeyCreated:
    """A new key of your organisation; the answer holds the key, which is never shown again."""
    key, secret = keys.create_key(session, principal, Role[body.role], body.expires_at)
    return KeyCreated(**key_out(key).model_dump(), key=secret)


@router.post("/{key_id}/revoke")
def revoke_key(key_id: IdPath, principal: Admin, session: SessionDep) -> KeyOut:
    """Revoke a key at once; the dashboard logins opened with it end too."""
    key = keys.revoke_key(session, keys.get_key(session, principal, key_id))
    return key_out(key)
