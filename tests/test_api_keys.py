"""An organisation's admins list, create and revoke its API keys over HTTP.

A key ends when it is revoked (its dashboard logins with it) or when it expires, which its holder
is told; its last use is recorded to the minute, not written on every request.

On SQLite; the expiry and the last use, times the database stores and compares, on PostgreSQL
too (``database_server``).
"""

from __future__ import annotations

import datetime as dt
import hashlib

import pytest
from sqlalchemy import func, select, update

from harness.api_helpers import API, Org, clients
from harness.dashboard_helpers import DASHBOARD, logged_in
from harness.live import LiveServer
from service.tables import ApiKey, DashboardSession

FIELDS = {"id", "prefix", "role", "created_at", "expires_at", "last_used_at", "revoked_at"}
NOT_VALID = "the API key is not valid (unknown, malformed or revoked)"


def prefix(key: str) -> str:
    return key.split("_")[1]


def listed(org: Org) -> dict[str, dict]:
    """The organisation's keys as its admin lists them, by prefix."""
    with org.client("admin") as admin:
        response = admin.get(f"{API}/keys")
    assert response.status_code == 200, response.text
    return {key["prefix"]: key for key in response.json()}


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    return sqlite_api_server


def parse(stamp: str | None) -> dt.datetime | None:
    return None if stamp is None else dt.datetime.fromisoformat(stamp)


def test_admins_list_create_and_revoke_their_organisations_keys(api_server: LiveServer):
    org = Org.create(api_server)
    keys = listed(org)
    assert set(keys) == {prefix(key) for key in org.keys.values()}
    assert {key["role"] for key in keys.values()} == {"admin", "ingest", "viewer"}
    assert all(set(key) == FIELDS for key in keys.values())
    with clients(org) as (admin, _, _):
        before = dt.datetime.now(dt.UTC)
        created = admin.post(f"{API}/keys", json={"role": "ingest"})
        assert created.status_code == 201, created.text
        new = created.json()
        assert (
            set(new) == FIELDS | {"key"} and new["role"] == "ingest" and new["prefix"] == prefix(new["key"])
        )
        assert before - dt.timedelta(seconds=5) <= parse(new["created_at"]) <= dt.datetime.now(dt.UTC)
        assert new["expires_at"] is None and new["revoked_at"] is None
        with api_server.client(new["key"]) as client:
            assert client.get(f"{API}/structures").status_code == 200
        listing = admin.get(f"{API}/keys")
        # Never the key again, nor its hash.
        assert new["key"] not in listing.text
        assert hashlib.sha256(new["key"].encode()).hexdigest() not in listing.text
        assert [key["id"] for key in listing.json()].count(new["id"]) == 1

        revoked = admin.post(f"{API}/keys/{new['id']}/revoke")
        assert revoked.status_code == 200, revoked.text
        revoked_at = parse(revoked.json()["revoked_at"])
        assert revoked_at is not None and revoked_at >= parse(new["created_at"])
        with api_server.client(new["key"]) as client:
            refused = client.get(f"{API}/structures")
        assert (refused.status_code, refused.json()["detail"]) == (401, NOT_VALID)
        again = admin.post(f"{API}/keys/{new['id']}/revoke")
        assert again.status_code == 200 and parse(again.json()["revoked_at"]) == revoked_at
    assert parse(listed(org)[new["prefix"]]["revoked_at"]) == revoked_at
    with org.client("ingest") as ingest:  # the organisation's other keys are untouched
        assert ingest.get(f"{API}/structures").status_code == 200


def test_an_admin_creates_keys_of_every_role_and_nothing_malformed(api_server: LiveServer):
    org = Org.create(api_server)
    with org.client("admin") as admin:
        for role in ("viewer", "ingest", "admin"):
            response = admin.post(f"{API}/keys", json={"role": role})
            assert response.status_code == 201 and response.json()["role"] == role, response.text
        count = len(admin.get(f"{API}/keys").json())
        past = (dt.datetime.now(dt.UTC) - dt.timedelta(minutes=1)).isoformat()
        refusals = [
            ({"role": "root"}, "role"),
            ({}, "role"),
            ({"role": "viewer", "expires_at": "2030-01-01T00:00:00"}, "give a timezone"),
            ({"role": "viewer", "expires_at": "tomorrow"}, "ISO 8601"),
            ({"role": "viewer", "expires_at": past}, "has passed; give a time in the future"),
            ({"role": "viewer", "key_hash": "0" * 64}, "key_hash"),
        ]
        for body, message in refusals:
            response = admin.post(f"{API}/keys", json=body)
            assert response.status_code == 422 and message in response.text, (body, response.text)
        assert len(admin.get(f"{API}/keys").json()) == count, "a refused key was stored"


def test_an_expired_key_is_refused_and_told_so(database_server: LiveServer):
    api_server = database_server
    org = Org.create(api_server)
    expires_at = dt.datetime.now(dt.UTC) + dt.timedelta(hours=1)
    with org.client("admin") as admin:
        created = admin.post(f"{API}/keys", json={"role": "viewer", "expires_at": expires_at.isoformat()})
    assert created.status_code == 201, created.text
    assert parse(created.json()["expires_at"]) == expires_at
    key = created.json()["key"]
    login = logged_in(api_server, key)
    with api_server.client(key) as client, login:
        assert client.get(f"{API}/structures").status_code == 200
        assert login.get(DASHBOARD).status_code == 200
        # The hour passes (moved here rather than waited for).
        expired_at = dt.datetime.now(dt.UTC) - dt.timedelta(seconds=1)
        with api_server.app.state.sessions() as session:
            session.execute(update(ApiKey).where(ApiKey.prefix == prefix(key)).values(expires_at=expired_at))
            session.commit()
        refused = client.get(f"{API}/structures")
        assert refused.status_code == 401 and refused.headers["www-authenticate"] == "Bearer"
        assert refused.json()["detail"] == (
            f"the API key expired at {expired_at:%Y-%m-%d %H:%M:%S} UTC; ask an admin for a new one"
        )
        assert login.get(DASHBOARD).status_code == 303, "a login outlived its key"
    # Someone without the whole key learns nothing about it: its prefix with another secret.
    with api_server.client(f"nw_{prefix(key)}_{'x' * 43}") as guesser:
        assert guesser.get(f"{API}/structures").json()["detail"] == NOT_VALID


def test_last_use_is_recorded_at_most_once_a_minute(database_server: LiveServer):
    api_server = database_server
    org = Org.create(api_server)
    viewer = prefix(org.keys["viewer"])
    assert listed(org)[viewer]["last_used_at"] is None
    started = dt.datetime.now(dt.UTC)
    with org.client("viewer") as client:
        assert client.get(f"{API}/structures").status_code == 200
        first = parse(listed(org)[viewer]["last_used_at"])
        assert first is not None and started - dt.timedelta(seconds=1) <= first <= dt.datetime.now(dt.UTC)
        for _ in range(5):
            assert client.get(f"{API}/structures").status_code == 200
        assert parse(listed(org)[viewer]["last_used_at"]) == first, "each use wrote the key"
        # A minute later (moved back here rather than waited for), the next use is recorded.
        with api_server.app.state.sessions() as session:
            earlier = first - dt.timedelta(seconds=61)
            session.execute(update(ApiKey).where(ApiKey.prefix == viewer).values(last_used_at=earlier))
            session.commit()
        assert client.get(f"{API}/structures").status_code == 200
    assert parse(listed(org)[viewer]["last_used_at"]) > first


def test_revoking_a_key_ends_its_dashboard_logins(api_server: LiveServer):
    org = Org.create(api_server)
    key_id = listed(org)[prefix(org.keys["viewer"])]["id"]
    first, second = logged_in(api_server, org.keys["viewer"]), logged_in(api_server, org.keys["viewer"])
    other = logged_in(api_server, org.keys["admin"])
    with first, second, other, org.client("admin") as admin:
        assert first.get(DASHBOARD).status_code == second.get(DASHBOARD).status_code == 200
        assert admin.post(f"{API}/keys/{key_id}/revoke").status_code == 200
        assert first.get(DASHBOARD).status_code == second.get(DASHBOARD).status_code == 303
        assert other.get(DASHBOARD).status_code == 200, "another key's login ended"
    with api_server.app.state.sessions() as session:
        logins = select(func.count()).where(DashboardSession.api_key_id == key_id)
        assert session.scalar(logins) == 0
    with api_server.client() as anonymous:  # and no new one opens
        response = anonymous.post(
            f"{DASHBOARD}/login", data={"api_key": org.keys["viewer"], "next": DASHBOARD}
        )
        assert response.status_code != 303
