"""Organisations never see one another, over every route of the API, on SQLite and PostgreSQL.

``TENANCY`` says, for each route, what a key of another organisation gets. A route that names an
object in its path answers another organisation's id exactly as it answers an id that does not
exist: the same status, the same message but for the number, so that an answer never tells
whether the id exists; with a key whose role is below the route's, the same 403 either way. A
route without an id lists, reads or changes the caller's own organisation alone. Nothing another
organisation's key sends changes what the first lists. The table is checked against the app's
routes: a new route without a row fails here.

Two organisations each hold one object of every kind (``harness.estates``): ours calls, theirs
is called on.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import pytest

from harness.api_helpers import API, Org, nothing_written
from harness.estates import MISSING, Estate, api_routes, body_for, build_estate, call
from harness.live import LiveServer

ROLES = ("viewer", "ingest", "admin")
# A route without an id: a listing shows none of theirs (the id their estate names below), a
# reading of the organisation's settings shows ours, a write changes ours alone.
LISTS = "lists ours alone"
READS = "reads ours"
WRITES = "writes ours alone"
# What a key of another organisation gets, route by route: for a route with ids, the 404's message
# (as for an id that does not exist), the first id the handler looks up named.
THEIR_STRUCTURE = "structure {structure_id} not found"
THEIR_SUBSCRIPTION = "e-mail subscription {subscription_id} not found"
TENANCY: dict[tuple[str, str], str | tuple[str, str]] = {
    ("POST", "/api/v1/structures"): WRITES,
    ("GET", "/api/v1/structures"): (LISTS, "structure_id"),
    ("GET", "/api/v1/structures/{structure_id}"): THEIR_STRUCTURE,
    ("PATCH", "/api/v1/structures/{structure_id}"): THEIR_STRUCTURE,
    ("GET", "/api/v1/structures/{structure_id}/verdicts"): THEIR_STRUCTURE,
    ("GET", "/api/v1/structures/{structure_id}/summary"): THEIR_STRUCTURE,
    ("GET", "/api/v1/structures/{structure_id}/models"): THEIR_STRUCTURE,
    ("POST", "/api/v1/structures/{structure_id}/models/baseline"): THEIR_STRUCTURE,
    ("POST", "/api/v1/structures/{structure_id}/models/fault-modes"): THEIR_STRUCTURE,
    ("POST", "/api/v1/structures/{structure_id}/models/pooled-baseline"): THEIR_STRUCTURE,
    ("POST", "/api/v1/structures/{structure_id}/models/pooled-fault-modes"): THEIR_STRUCTURE,
    ("POST", "/api/v1/structures/{structure_id}/models/vector-fault-modes"): THEIR_STRUCTURE,
    ("POST", "/api/v1/structures/{structure_id}/models/{model_id}/activate"): THEIR_STRUCTURE,
    ("POST", "/api/v1/structures/{structure_id}/records"): THEIR_STRUCTURE,
    ("POST", "/api/v1/structures/{structure_id}/record-sets"): THEIR_STRUCTURE,
    ("POST", "/api/v1/records/{record_id}/inspect"): "record {record_id} not found",
    ("GET", "/api/v1/verdicts/{verdict_id}"): "verdict {verdict_id} not found",
    ("POST", "/api/v1/structures/{structure_id}/refinements"): THEIR_STRUCTURE,
    ("GET", "/api/v1/structures/{structure_id}/refinements"): THEIR_STRUCTURE,
    ("GET", "/api/v1/refinements/{refinement_id}"): "refinement {refinement_id} not found",
    ("POST", "/api/v1/structures/{structure_id}/schedules"): THEIR_STRUCTURE,
    ("GET", "/api/v1/structures/{structure_id}/schedules"): THEIR_STRUCTURE,
    ("DELETE", "/api/v1/structures/{structure_id}/schedules/{schedule_id}"): THEIR_STRUCTURE,
    ("GET", "/api/v1/keys"): (LISTS, "key_id"),
    ("POST", "/api/v1/keys"): WRITES,
    ("POST", "/api/v1/keys/{key_id}/revoke"): "API key {key_id} not found",
    ("GET", "/api/v1/jobs"): (LISTS, "job_id"),
    ("GET", "/api/v1/jobs/{job_id}"): "job {job_id} not found",
    ("GET", "/api/v1/alarms"): (LISTS, "alarm_id"),
    ("GET", "/api/v1/alarms/{alarm_id}"): "alarm {alarm_id} not found",
    ("POST", "/api/v1/alarms/{alarm_id}/acknowledge"): "alarm {alarm_id} not found",
    ("POST", "/api/v1/alarms/{alarm_id}/resolve"): "alarm {alarm_id} not found",
    ("GET", "/api/v1/structures/{structure_id}/alarm-rules"): THEIR_STRUCTURE,
    ("PUT", "/api/v1/structures/{structure_id}/alarm-rules"): THEIR_STRUCTURE,
    ("POST", "/api/v1/webhooks"): WRITES,
    ("GET", "/api/v1/webhooks"): (LISTS, "webhook_id"),
    ("DELETE", "/api/v1/webhooks/{webhook_id}"): "webhook {webhook_id} not found",
    ("GET", "/api/v1/webhooks/{webhook_id}/deliveries"): "webhook {webhook_id} not found",
    ("POST", "/api/v1/email-subscriptions"): WRITES,
    ("GET", "/api/v1/email-subscriptions"): (LISTS, "subscription_id"),
    ("DELETE", "/api/v1/email-subscriptions/{subscription_id}"): THEIR_SUBSCRIPTION,
    ("GET", "/api/v1/email-subscriptions/{subscription_id}/deliveries"): THEIR_SUBSCRIPTION,
    ("GET", "/api/v1/retention"): READS,
    ("PUT", "/api/v1/retention"): WRITES,
}
# Their retention, unlike anyone else's: what ours reads must not be it.
THEIR_RETENTION = {"signal_days": 91, "verdict_days": 731}


@pytest.fixture(scope="module")
def ours(api_server: LiveServer) -> Estate:
    return build_estate(api_server, seed=51)


@pytest.fixture(scope="module")
def theirs(api_server: LiveServer) -> Estate:
    estate = build_estate(api_server, seed=52)
    with estate.org.client("admin") as admin:
        response = admin.put(f"{API}/retention", json=THEIR_RETENTION)
        assert response.status_code == 200, response.text
    return estate


def listed(answer: Any) -> list[dict]:
    """The items of a listing, paged (``{"items": …}``) or not."""
    return answer["items"] if isinstance(answer, dict) else answer


def organisation_view(org: Org) -> dict[str, Any]:
    """What the organisation's admin lists outside its structures (a key's last use left out: the
    view's own requests move it)."""
    with org.client("admin") as admin:
        view = {
            path: admin.get(f"{API}{path}").json()
            for path in (
                "/keys",
                "/jobs",
                "/alarms?limit=1000",
                "/webhooks",
                "/email-subscriptions",
                "/retention",
            )
        }
    view["/keys"] = [{k: v for k, v in key.items() if k != "last_used_at"} for key in view["/keys"]]
    return view


@contextmanager
def untouched(estate: Estate) -> Iterator[None]:
    """Nothing inside the block changed what ``estate``'s organisation lists, in its structure or
    outside it."""
    before = organisation_view(estate.org)
    with nothing_written(estate.org, estate.structure_id):
        yield
    assert organisation_view(estate.org) == before, "another organisation's request changed theirs"


def test_the_table_has_a_row_for_every_route(api_server: LiveServer):
    assert set(TENANCY) == set(api_routes(api_server))


def test_their_ids_are_answered_as_ids_that_do_not_exist(
    api_server: LiveServer, ours: Estate, theirs: Estate
):
    """Every route with ids, every role of ours: their ids get the answer an id of nothing gets,
    the number aside; for our admin (whose role every route admits) the table's 404."""
    missing = dict.fromkeys(theirs.ids(), MISSING)
    failures = []
    with untouched(theirs):
        for method, path in api_routes(api_server):
            if "{" not in path:
                continue
            for role in ROLES:
                with ours.org.client(role) as client:
                    answer = call(client, method, path, theirs.ids(), body_for(path, theirs))
                    nothing = call(client, method, path, missing, body_for(path, theirs))
                same = (answer.status_code, re.sub(r"\d+", "N", answer.text)) == (
                    nothing.status_code,
                    re.sub(r"\d+", "N", nothing.text),
                )
                if role == "admin":
                    expected = {"detail": TENANCY[method, path].format(**theirs.ids())}
                    same = same and (answer.status_code, answer.json()) == (404, expected)
                if not same or theirs.structure_name in answer.text or theirs.org.name in answer.text:
                    failures.append(f"{role} {method} {path}: {answer.status_code} {answer.text[:120]}")
    assert not failures, "\n".join(failures)


def test_routes_without_ids_list_read_and_change_ours_alone(
    api_server: LiveServer, ours: Estate, theirs: Estate
):
    failures = []
    with untouched(theirs), ours.org.client("admin") as admin:
        for method, path in api_routes(api_server):
            row = TENANCY[method, path]
            if "{" in path:
                continue
            response = call(admin, method, path, {}, body_for(path, ours))
            if row == READS:
                right = response.status_code == 200 and response.json() != THEIR_RETENTION
            elif row == WRITES:  # refused or done: their view is checked unchanged at the end
                right = response.status_code < 500
            else:
                _, their_id = row
                ids = {item["id"] for item in listed(response.json())}
                right = response.status_code == 200 and getattr(ours, their_id) in ids
                right = right and getattr(theirs, their_id) not in ids
            if not right:
                failures.append(f"{method} {path}: {response.status_code} {response.text[:120]}")
    assert not failures, "\n".join(failures)


def test_their_ids_inside_our_urls_and_bodies_are_not_found(ours: Estate, theirs: Estate):
    """Our structure with their model or records: as unknown as ids that do not exist."""
    with (
        untouched(theirs),
        nothing_written(ours.org, ours.structure_id),
        ours.org.client("admin") as admin,
    ):
        base = f"{API}/structures/{ours.structure_id}/models"
        for model_id in (theirs.model_id, MISSING):
            response = admin.post(f"{base}/{model_id}/activate")
            assert (response.status_code, response.json()) == (
                404,
                {"detail": f"model version {model_id} not found"},
            )
        for record_id in (theirs.record_id, MISSING):
            response = admin.post(f"{base}/baseline", json={"record_ids": [record_id]})
            assert (response.status_code, response.json()) == (
                404,
                {"detail": f"record {record_id} not found"},
            )
            experiments = [*ours.training[:2], {"record_id": record_id, "k": 30.0}]
            response = admin.post(
                f"{base}/fault-modes",
                json={"name": "k2", "k_min": -32.0, "k_max": 32.0, "experiments": experiments},
            )
            assert (response.status_code, response.json()) == (
                404,
                {"detail": f"record {record_id} not found"},
            )
        refinements = f"{API}/structures/{ours.structure_id}/refinements"
        for record_id in (theirs.record_id, MISSING):
            body = {"record_id": record_id, "base_model_id": ours.baseline_id}
            response = admin.post(refinements, json=body)
            assert (response.status_code, response.json()) == (
                404,
                {"detail": f"record {record_id} not found"},
            )
        for model_id in (theirs.baseline_id, MISSING):
            body = {"record_id": ours.record_id, "base_model_id": model_id}
            response = admin.post(refinements, json=body)
            assert (response.status_code, response.json()) == (
                404,
                {"detail": f"model version {model_id} not found"},
            )
        for record_id in (theirs.record_id, MISSING):  # a refinement's test records
            body = {
                "record_ids": [ours.record_id],
                "test_record_ids": [record_id],
                "base_model_id": ours.baseline_id,
            }
            response = admin.post(refinements, json=body)
            assert (response.status_code, response.json()) == (
                404,
                {"detail": f"record {record_id} not found"},
            )
        for structure_id in (theirs.structure_id, MISSING):  # a structure named in the query
            response = admin.get(f"{API}/alarms", params={"structure_id": structure_id})
            assert (response.status_code, response.json()) == (
                404,
                {"detail": f"structure {structure_id} not found"},
            )
        for schedule_id in (theirs.schedule_id, MISSING):
            response = admin.delete(f"{API}/structures/{ours.structure_id}/schedules/{schedule_id}")
            assert (response.status_code, response.json()) == (
                404,
                {"detail": f"schedule {schedule_id} not found"},
            )
