"""Roles through HTTP, on SQLite: the role check runs before anything is read from the database,
so no database decides it.

The rule, from ``service/api/deps.py``: the role check is a dependency, so it runs before the
handler looks anything up. A key whose role is below what a route needs gets 403 whatever the
ids (its own, another organisation's, or none at all), so a role failure never reveals whether
an id exists. What a key of another organisation gets is tests/test_tenancy.py's.
"""

from __future__ import annotations

import pytest

from harness.api_helpers import (
    API,
    RIG_TERMS,
    clients,
    create_structure,
    json_body,
    nothing_written,
    post_record,
    simulated,
    train_fault_mode,
    upload_simulated,
)
from harness.estates import MISSING, Estate, api_routes, body_for, build_estate, call
from harness.live import LiveServer

RANK = {"viewer": 1, "ingest": 2, "admin": 3}
ROLES = tuple(RANK)
# The role each route needs: the access policy under test. Every route of the app must be here.
POLICY = {
    ("POST", "/api/v1/structures"): "admin",
    ("GET", "/api/v1/structures"): "viewer",
    ("GET", "/api/v1/structures/{structure_id}"): "viewer",
    ("PATCH", "/api/v1/structures/{structure_id}"): "admin",
    ("GET", "/api/v1/structures/{structure_id}/verdicts"): "viewer",
    ("GET", "/api/v1/structures/{structure_id}/summary"): "viewer",
    ("GET", "/api/v1/structures/{structure_id}/models"): "viewer",
    ("POST", "/api/v1/structures/{structure_id}/models/baseline"): "admin",
    ("POST", "/api/v1/structures/{structure_id}/models/fault-modes"): "admin",
    ("POST", "/api/v1/structures/{structure_id}/models/pooled-baseline"): "admin",
    ("POST", "/api/v1/structures/{structure_id}/models/pooled-fault-modes"): "admin",
    ("POST", "/api/v1/structures/{structure_id}/models/vector-fault-modes"): "admin",
    ("POST", "/api/v1/structures/{structure_id}/models/{model_id}/activate"): "admin",
    ("POST", "/api/v1/structures/{structure_id}/records"): "ingest",
    ("POST", "/api/v1/structures/{structure_id}/record-sets"): "ingest",
    ("POST", "/api/v1/records/{record_id}/inspect"): "ingest",
    ("GET", "/api/v1/verdicts/{verdict_id}"): "viewer",
    ("POST", "/api/v1/structures/{structure_id}/refinements"): "admin",
    ("GET", "/api/v1/structures/{structure_id}/refinements"): "viewer",
    ("GET", "/api/v1/refinements/{refinement_id}"): "viewer",
    ("POST", "/api/v1/structures/{structure_id}/schedules"): "admin",
    ("GET", "/api/v1/structures/{structure_id}/schedules"): "viewer",
    ("DELETE", "/api/v1/structures/{structure_id}/schedules/{schedule_id}"): "admin",
    ("GET", "/api/v1/keys"): "admin",
    ("POST", "/api/v1/keys"): "admin",
    ("POST", "/api/v1/keys/{key_id}/revoke"): "admin",
    ("GET", "/api/v1/jobs"): "admin",
    ("GET", "/api/v1/jobs/{job_id}"): "admin",
    ("GET", "/api/v1/alarms"): "viewer",
    ("GET", "/api/v1/alarms/{alarm_id}"): "viewer",
    ("POST", "/api/v1/alarms/{alarm_id}/acknowledge"): "admin",
    ("POST", "/api/v1/alarms/{alarm_id}/resolve"): "admin",
    ("GET", "/api/v1/structures/{structure_id}/alarm-rules"): "viewer",
    ("PUT", "/api/v1/structures/{structure_id}/alarm-rules"): "admin",
    ("POST", "/api/v1/webhooks"): "admin",
    ("GET", "/api/v1/webhooks"): "admin",
    ("DELETE", "/api/v1/webhooks/{webhook_id}"): "admin",
    ("GET", "/api/v1/webhooks/{webhook_id}/deliveries"): "admin",
    ("POST", "/api/v1/email-subscriptions"): "admin",
    ("GET", "/api/v1/email-subscriptions"): "admin",
    ("DELETE", "/api/v1/email-subscriptions/{subscription_id}"): "admin",
    ("GET", "/api/v1/email-subscriptions/{subscription_id}/deliveries"): "admin",
    ("GET", "/api/v1/retention"): "admin",
    ("PUT", "/api/v1/retention"): "admin",
}
# The routes outside /api/v1: no organisation's data, so no API key. The probes, and the metrics
# (fleet-wide counts; NARXWATCH_METRICS_TOKEN guards them when set, and it is unset here).
PUBLIC = {("GET", "/healthz"), ("GET", "/readyz"), ("GET", "/metrics")}


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    return sqlite_api_server


@pytest.fixture(scope="module")
def ours(api_server: LiveServer) -> Estate:
    return build_estate(api_server, seed=51)


def test_the_policy_covers_every_route(api_server: LiveServer):
    assert set(api_routes(api_server)) == set(POLICY)


def test_the_routes_outside_the_api_are_public(api_server: LiveServer):
    documented = {
        (method.upper(), path)
        for path, item in api_server.app.openapi()["paths"].items()
        if not path.startswith(API)
        for method in item
    }
    assert documented == PUBLIC
    with api_server.client() as anonymous:
        for method, path in PUBLIC:
            assert anonymous.request(method, path).status_code == 200, path


def test_a_role_failure_does_not_reveal_whether_an_id_exists(api_server: LiveServer, ours: Estate):
    """Below the route's role, our ids and ids of nothing get the same answer (another
    organisation's ids get it too: tests/test_tenancy.py)."""
    missing = dict.fromkeys(ours.ids(), MISSING)
    checked = 0
    with nothing_written(ours.org, ours.structure_id):
        for method, path in api_routes(api_server):
            for role in ROLES:
                if RANK[role] >= RANK[POLICY[method, path]]:
                    continue
                answers = set()
                for ids in (ours.ids(), missing):
                    with ours.org.client(role) as client:
                        response = call(client, method, path, ids, body_for(path, ours))
                    answers.add((response.status_code, response.text))
                (answer,) = answers
                status, text = answer
                assert status == 403, (role, method, path, text)
                needed = POLICY[method, path]
                assert f"this needs a key of role '{needed}' or higher; yours is '{role}'" in text
                checked += 1
    # viewer: 29 admin and 3 ingest routes; ingest: 29 admin routes.
    assert checked == sum(RANK[role] < RANK[needed] for needed in POLICY.values() for role in ROLES) == 61


# --- what each role may do, on our own objects -------------------------------------------------


def test_viewer_reads_but_cannot_write(ours: Estate):
    sid = ours.structure_id
    with ours.org.client("viewer") as viewer:
        for path in (
            "/structures",
            f"/structures/{sid}",
            f"/structures/{sid}/models",
            f"/structures/{sid}/verdicts",
            f"/structures/{sid}/summary",
            f"/verdicts/{ours.verdict_id}",
        ):
            assert viewer.get(API + path).status_code == 200, path
        with nothing_written(ours.org, sid):
            refusals = [
                (post_record(viewer, sid, json_body(300)), "ingest"),
                (viewer.post(f"{API}/records/{ours.record_id}/inspect"), "ingest"),
                (viewer.post(f"{API}/structures", json={"name": "mine", "fs": 1500.0}), "admin"),
                (
                    viewer.post(
                        f"{API}/structures/{sid}/models/baseline", json={"record_ids": [ours.record_id]}
                    ),
                    "admin",
                ),
                (
                    viewer.post(
                        f"{API}/structures/{sid}/models/fault-modes", json=body_for("/fault-modes", ours)
                    ),
                    "admin",
                ),
                (viewer.post(f"{API}/structures/{sid}/models/{ours.model_id}/activate"), "admin"),
            ]
            for response, needed in refusals:
                assert response.status_code == 403, response.text
                assert (
                    response.json()["detail"]
                    == f"this needs a key of role '{needed}' or higher; yours is 'viewer'"
                )


def test_ingest_uploads_and_inspects_but_cannot_administer(ours: Estate):
    sid = ours.structure_id
    with ours.org.client("ingest") as ingest:
        uploaded = upload_simulated(ingest, sid, simulated("k2", 20.0, [53, 1]), inspect="true")
        assert uploaded["created"] and uploaded["verdict"]["record_id"] == uploaded["id"]
        record = post_record(ingest, sid, json_body(2000))
        assert record.status_code == 201, record.text
        inspected = ingest.post(f"{API}/records/{record.json()['id']}/inspect")
        assert inspected.status_code == 200, inspected.text
        assert inspected.json()["model_versions"] == [{"id": ours.model_id, "name": "k2", "version": 1}]
        with nothing_written(ours.org, sid):
            refusals = [
                ingest.post(f"{API}/structures", json={"name": "mine", "fs": 1500.0}),
                ingest.post(f"{API}/structures/{sid}/models/baseline", json={"record_ids": [ours.record_id]}),
                ingest.post(
                    f"{API}/structures/{sid}/models/fault-modes", json=body_for("/fault-modes", ours)
                ),
                ingest.post(f"{API}/structures/{sid}/models/{ours.model_id}/activate"),
            ]
            for response in refusals:
                assert response.status_code == 403, response.text
                assert (
                    response.json()["detail"]
                    == "this needs a key of role 'admin' or higher; yours is 'ingest'"
                )


def test_admin_can_do_everything(ours: Estate):
    with clients(ours.org) as (admin, _, viewer):
        structure = create_structure(admin, "admin-made")["id"]
        model = train_fault_mode(admin, admin, structure, "k2", seed=54)  # uploads with the admin key
        record = post_record(admin, structure, json_body(2000))
        assert record.status_code == 201, record.text
        verdict = admin.post(f"{API}/records/{record.json()['id']}/inspect")
        assert verdict.status_code == 200, verdict.text
        activated = admin.post(f"{API}/structures/{structure}/models/{model['id']}/activate")
        assert activated.status_code == 200 and activated.json()["active"] is True
        baseline = admin.post(
            f"{API}/structures/{structure}/models/baseline",
            json={"record_ids": [record.json()["id"]], "terms": RIG_TERMS},
        )
        assert baseline.status_code == 201, baseline.text
        assert viewer.get(f"{API}/verdicts/{verdict.json()['id']}").json() == verdict.json()
        names = {
            (m["name"], m["version"], m["active"])
            for m in viewer.get(f"{API}/structures/{structure}/models").json()
        }
        assert names == {("k2", 1, True), ("baseline", 1, True)}
