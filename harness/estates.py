"""An organisation with one object of every kind, and every route of the API to call on it.

The route tables (``tests/test_api_access.py``'s roles, ``tests/test_tenancy.py``'s
organisations) call each route with an estate's ids and a valid body, so that only the role check
and the lookups decide the answer.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from dataclasses import dataclass

import httpx
from sqlalchemy import select

from harness.api_helpers import (
    API,
    RIG_TERMS,
    Org,
    clients,
    create_structure,
    experiments,
    json_body,
    npz_bytes,
    post_record,
    simulated,
    upload_simulated,
    wait_for,
)
from harness.live import LiveServer
from service.db import transaction
from service.tables import EmailSubscription, Organisation

# Never due while the tests run: a schedule that ran would write verdicts under their feet.
SCHEDULE = {"action": "inspect_pending", "interval_seconds": 3600, "first_run_at": "2099-01-01T00:00:00Z"}
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
            json={"name": "k2", "k_min": -32.0, "k_max": 32.0, "experiments": training, "terms": RIG_TERMS},
        )
        assert response.status_code == 201, response.text
        model_id = response.json()["id"]
        # One faulty verdict opens an alarm under this rule.
        rules = {"rules": [{"kind": "persistence", "k": 1, "m": 1}]}
        assert admin.put(f"{API}/structures/{sid}/alarm-rules", json=rules).status_code == 200
        record = upload_simulated(ingest, sid, simulated("k2", 10.0, [seed, 99]), inspect="true")
        (alarm,) = admin.get(f"{API}/alarms").json()["items"]
        response = admin.post(
            f"{API}/structures/{sid}/models/baseline", json={"record_ids": [record["id"]], "terms": RIG_TERMS}
        )
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
    assert routes == documented and len(routes) == 44, routes
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
    if path.endswith("/structures/{structure_id}"):  # its description as created: changes nothing
        return {"description": ""}
    if path.endswith("/pooled-baseline"):
        return {"record_ids": [experiment["record_id"] for experiment in estate.training], "terms": RIG_TERMS}
    if path.endswith("/pooled-fault-modes") or path.endswith("/vector-fault-modes"):
        return {"name": "k2", "experiments": estate.training}
    if path.endswith("/baseline"):
        return {"record_ids": [estate.record_id], "terms": RIG_TERMS}
    if path.endswith("/fault-modes"):
        return {
            "name": "k2",
            "k_min": -32.0,
            "k_max": 32.0,
            "experiments": estate.training,
            "terms": RIG_TERMS,
        }
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
