"""Roles and tenancy through HTTP, on SQLite and PostgreSQL.

The rule, from ``service/api/deps.py`` and the domain's lookups: the role check is a dependency,
so it runs before the handler looks anything up. A key whose role is below what a route needs
gets 403 whatever the ids (its own, another organisation's, or none at all), so a role failure
never reveals whether an id exists. A key with a sufficient role gets 404 for any id of another
organisation, with the same message as for an id that does not exist.
"""

from __future__ import annotations

import re
import uuid
from collections.abc import Iterator
from dataclasses import dataclass

import httpx
import pytest
from sqlalchemy import select

from harness.api_helpers import (
    API,
    Org,
    clients,
    create_structure,
    experiments,
    json_body,
    nothing_written,
    npz_bytes,
    post_record,
    simulated,
    train_fault_mode,
    upload_simulated,
    wait_for,
)
from harness.live import LiveServer
from service.db import transaction
from service.tables import EmailSubscription, Organisation

RANK = {"viewer": 1, "ingest": 2, "admin": 3}
ROLES = tuple(RANK)
# The role each route needs: the access policy under test. Every route of the app must be here.
POLICY = {
    ("POST", "/api/v1/structures"): "admin",
    ("GET", "/api/v1/structures"): "viewer",
    ("GET", "/api/v1/structures/{structure_id}"): "viewer",
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
# Never due while the tests run: a schedule that ran would write verdicts under their feet.
SCHEDULE = {"action": "inspect_pending", "interval_seconds": 3600, "first_run_at": "2099-01-01T00:00:00Z"}
# The routes outside /api/v1: no organisation's data, so no API key. The probes, and the metrics
# (fleet-wide counts; NARXWATCH_METRICS_TOKEN guards them when set, and it is unset here).
PUBLIC = {("GET", "/healthz"), ("GET", "/readyz"), ("GET", "/metrics")}
MISSING = 10**6  # an id no object has


@dataclass
class Estate:
    """An organisation with a trained structure, a stored record, a verdict, a refinement, a
    schedule, a job, an alarm, a webhook and an e-mail subscription."""

    org: Org
    structure_id: int
    structure_name: str
    training: list[dict]
    model_id: int
    record_id: int
    verdict_id: int
    baseline_id: int
    refinement_id: int
    schedule_id: int
    key_id: int
    job_id: int
    alarm_id: int
    webhook_id: int
    subscription_id: int

    def ids(self) -> dict[str, int]:
        return {
            "structure_id": self.structure_id,
            "model_id": self.model_id,
            "record_id": self.record_id,
            "verdict_id": self.verdict_id,
            "refinement_id": self.refinement_id,
            "schedule_id": self.schedule_id,
            "key_id": self.key_id,
            "job_id": self.job_id,
            "alarm_id": self.alarm_id,
            "webhook_id": self.webhook_id,
            "subscription_id": self.subscription_id,
        }


def build_estate(server: LiveServer, seed: int) -> Estate:
    org = Org.create(server)
    with clients(org) as (admin, ingest, _):
        structure = create_structure(admin)
        sid = structure["id"]
        training = experiments(ingest, sid, "k2", seed)
        response = admin.post(
            f"{API}/structures/{sid}/models/fault-modes",
            json={"name": "k2", "k_min": -32.0, "k_max": 32.0, "experiments": training},
        )
        assert response.status_code == 201, response.text
        model_id = response.json()["id"]
        # One faulty verdict opens an alarm under this rule.
        rules = {"rules": [{"kind": "persistence", "k": 1, "m": 1}]}
        assert admin.put(f"{API}/structures/{sid}/alarm-rules", json=rules).status_code == 200
        record = upload_simulated(ingest, sid, simulated("k2", 10.0, [seed, 99]), inspect="true")
        (alarm,) = admin.get(f"{API}/alarms").json()["items"]
        response = admin.post(f"{API}/structures/{sid}/models/baseline", json={"record_ids": [record["id"]]})
        assert response.status_code == 201, response.text
        baseline_id = response.json()["id"]
        response = admin.post(
            f"{API}/structures/{sid}/refinements",
            json={"record_id": record["id"], "base_model_id": baseline_id},
        )
        assert response.status_code == 201, response.text
        refinement_id = response.json()["id"]
        response = admin.post(f"{API}/structures/{sid}/schedules", json=SCHEDULE)
        assert response.status_code == 201, response.text
        later = simulated("k2", -10.0, [seed, 98])
        queued = post_record(
            ingest, sid, npz_bytes(x=later.x, y=later.y, fs=later.fs), "application/x-npz", inspect="queue"
        )
        assert queued.status_code == 202, queued.text
        (job,) = admin.get(f"{API}/jobs").json()["items"]
        assert job["args"] == {"record_id": queued.json()["id"]}
        # Done before the tests look: a job still running would write under their feet.
        wait_for(
            lambda: admin.get(f"{API}/jobs/{job['id']}").json()["state"] == "done", 60, "the job never ran"
        )
        viewer_prefix = org.keys["viewer"].split("_")[1]
        (key_id,) = [key["id"] for key in admin.get(f"{API}/keys").json() if key["prefix"] == viewer_prefix]
        webhook = admin.post(f"{API}/webhooks", json=body_for("/webhooks", None))
        assert webhook.status_code == 201, webhook.text
    # The shared servers send no e-mail (no SMTP relay, so the API refuses subscriptions): one is
    # stored directly, for the routes that look one up.
    with transaction(server.app.state.sessions) as session:
        organisation_id = session.scalar(select(Organisation.id).where(Organisation.name == org.name))
        subscription = EmailSubscription(
            organisation_id=organisation_id, addresses=["ops@example.com"], events=["alarm.opened"]
        )
        session.add(subscription)
        session.flush()
        subscription_id = subscription.id
    return Estate(
        org,
        sid,
        structure["name"],
        training,
        model_id,
        record["id"],
        record["verdict"]["id"],
        baseline_id,
        refinement_id,
        response.json()["id"],
        key_id,
        job["id"],
        alarm["id"],
        webhook.json()["id"],
        subscription_id,
    )


@pytest.fixture(scope="module")
def ours(api_server: LiveServer) -> Estate:
    return build_estate(api_server, seed=51)


@pytest.fixture(scope="module")
def theirs(api_server: LiveServer) -> Estate:
    return build_estate(api_server, seed=52)


def api_routes(server: LiveServer) -> list[tuple[str, str]]:
    """(method, path) of every route of the app under /api/v1, checked against its OpenAPI."""

    def walk(routes) -> Iterator[tuple[str, str]]:
        for route in routes:
            if hasattr(route, "effective_candidates"):  # FastAPI keeps an included router as one route
                yield from walk(route.effective_candidates())
            elif getattr(route, "path", "").startswith(API):
                yield from ((method, route.path) for method in route.methods)

    routes = sorted(set(walk(server.app.routes)))
    documented = sorted(
        (method.upper(), path)
        for path, item in server.app.openapi()["paths"].items()
        if path.startswith(API)
        for method in item
    )
    assert routes == documented and len(routes) == 43, routes
    return routes


def body_for(path: str, estate: Estate | None) -> dict | None:
    """A valid body for ``path`` referring to ``estate``'s records, so that validation passes
    and only the lookups decide the answer."""
    if path.endswith("/webhooks"):
        return {"url": "https://93.184.215.14/hooks", "secret": "s" * 32, "events": ["alarm.opened"]}
    if path.endswith("/email-subscriptions"):
        return {"addresses": ["ops@example.com"], "events": ["alarm.opened"]}
    if path.endswith("/retention"):
        return {"signal_days": 90, "verdict_days": 730}
    assert estate is not None
    if path.endswith("/structures"):
        return {"name": f"new-{uuid.uuid4().hex[:8]}", "fs": 1500.0}
    if path.endswith("/pooled-baseline"):
        return {"record_ids": [experiment["record_id"] for experiment in estate.training]}
    if path.endswith("/pooled-fault-modes") or path.endswith("/vector-fault-modes"):
        return {"name": "k2", "experiments": estate.training}
    if path.endswith("/baseline"):
        return {"record_ids": [estate.record_id]}
    if path.endswith("/fault-modes"):
        return {"name": "k2", "k_min": -32.0, "k_max": 32.0, "experiments": estate.training}
    if path.endswith("/records"):
        return json_body(300)
    if path.endswith("/refinements"):
        return {"record_id": estate.record_id, "base_model_id": estate.baseline_id}
    if path.endswith("/schedules"):
        return SCHEDULE
    if path.endswith("/keys"):
        return {"role": "viewer"}
    if path.endswith("/alarm-rules"):
        return {"rules": [{"kind": "severity"}]}
    if path.endswith(("/acknowledge", "/resolve")):
        return {"note": "seen"}
    return None


def call(
    client: httpx.Client, method: str, path: str, ids: dict[str, int], body: dict | None
) -> httpx.Response:
    return client.request(method, path.format(**ids), json=body)


def first_lookup(path: str, ids: dict[str, int]) -> str:
    """What a handler looks up first, as its 404 names it: the structure, else the record,
    verdict, refinement, API key or job."""
    names = ("structure", "record", "verdict", "refinement", "job", "alarm")
    labels = {name: name for name in names} | {"key": "API key", "webhook": "webhook"}
    labels["subscription"] = "e-mail subscription"
    for name, label in labels.items():
        if "{" + name + "_id}" in path:
            return f"{label} {ids[name + '_id']} not found"
    raise AssertionError(path)


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


def test_other_organisations_ids_are_not_found(api_server: LiveServer, ours: Estate, theirs: Estate):
    """Every route, every role of ours, with their ids: 403 below the route's role, else 404."""
    failures = []
    with nothing_written(theirs.org, theirs.structure_id):
        for method, path in api_routes(api_server):
            if "{" not in path:
                continue
            for role in ROLES:
                with ours.org.client(role) as client:
                    response = call(client, method, path, theirs.ids(), body_for(path, theirs))
                detail = response.json().get("detail")
                if RANK[role] < RANK[POLICY[method, path]]:
                    right = response.status_code == 403 and f"yours is '{role}'" in detail
                else:
                    right = response.status_code == 404 and detail == first_lookup(path, theirs.ids())
                if not right:
                    failures.append(f"{role} {method} {path}: {response.status_code} {response.text[:120]}")
    assert not failures, "\n".join(failures)


def test_their_ids_inside_our_urls_and_bodies_are_not_found(ours: Estate, theirs: Estate):
    """Our structure with their model or records: as unknown as ids that do not exist."""
    with (
        nothing_written(theirs.org, theirs.structure_id),
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
        for schedule_id in (theirs.schedule_id, MISSING):
            response = admin.delete(f"{API}/structures/{ours.structure_id}/schedules/{schedule_id}")
            assert (response.status_code, response.json()) == (
                404,
                {"detail": f"schedule {schedule_id} not found"},
            )


def test_listing_shows_only_our_structures(ours: Estate, theirs: Estate):
    for role in ROLES:
        with ours.org.client(role) as client:
            listed = client.get(f"{API}/structures").json()
        assert [s["id"] for s in listed] == [ours.structure_id]
        assert theirs.structure_name not in {s["name"] for s in listed}


def test_a_role_failure_does_not_reveal_whether_an_id_exists(
    api_server: LiveServer, ours: Estate, theirs: Estate
):
    """Below the route's role, our ids, their ids and ids of nothing get the same answer."""
    missing = dict.fromkeys(ours.ids(), MISSING)
    checked = 0
    with nothing_written(ours.org, ours.structure_id), nothing_written(theirs.org, theirs.structure_id):
        for method, path in api_routes(api_server):
            for role in ROLES:
                if RANK[role] >= RANK[POLICY[method, path]]:
                    continue
                answers = set()
                for ids, estate in ((ours.ids(), ours), (theirs.ids(), theirs), (missing, ours)):
                    with ours.org.client(role) as client:
                        response = call(client, method, path, ids, body_for(path, estate))
                    answers.add((response.status_code, response.text))
                (answer,) = answers
                status, text = answer
                assert status == 403, (role, method, path, text)
                needed = POLICY[method, path]
                assert f"this needs a key of role '{needed}' or higher; yours is '{role}'" in text
                checked += 1
    # viewer: 25 admin and 3 ingest routes; ingest: 25 admin routes.
    assert checked == sum(RANK[role] < RANK[needed] for needed in POLICY.values() for role in ROLES) == 59


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
            f"{API}/structures/{structure}/models/baseline", json={"record_ids": [record.json()["id"]]}
        )
        assert baseline.status_code == 201, baseline.text
        assert viewer.get(f"{API}/verdicts/{verdict.json()['id']}").json() == verdict.json()
        names = {
            (m["name"], m["version"], m["active"])
            for m in viewer.get(f"{API}/structures/{structure}/models").json()
        }
        assert names == {("k2", 1, True), ("baseline", 1, True)}


def test_error_messages_name_no_other_organisation(ours: Estate, theirs: Estate):
    """A 404 for their structure reads exactly like one for a structure that never existed."""
    with ours.org.client("admin") as admin:
        theirs_answer = admin.get(f"{API}/structures/{theirs.structure_id}").json()["detail"]
        missing_answer = admin.get(f"{API}/structures/{MISSING}").json()["detail"]
    assert (
        re.sub(r"\d+", "N", theirs_answer) == re.sub(r"\d+", "N", missing_answer) == "structure N not found"
    )
    assert theirs.structure_name not in theirs_answer
