"""Schemathesis against the served OpenAPI schema: no request may get a server error.

Every operation of ``/openapi.json`` is fuzzed over HTTP against the live server, on SQLite and
PostgreSQL, with an admin key of an organisation that owns a trained structure with records and
verdicts. Cases are generated with and without the owned ids in the path (random ids mostly
reach a 404; the owned ones reach the filters, parsers and training behind it), in Schemathesis'
positive and negative modes. Only ``not_a_server_error`` is checked: a 5xx is a service bug, and
the failure shows the request as a curl command.

Schemathesis' own pytest integration (``schemathesis.pytest.from_fixture``) does not run under
the installed pytest 9 (it sets ``Function._nodeid``), so each operation gets a Hypothesis test
built from its strategy here.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error

from harness.api_helpers import API, Org, clients, create_structure, json_body, post_record, train_fault_mode
from harness.live import LiveServer
from service.api.app import create_app
from service.config import Settings

# The operations, read from the app itself (an unserved instance; the tests use the served schema).
OPERATIONS = sorted(
    (method.upper(), path)
    for path, item in create_app(Settings(database_url="sqlite://")).openapi()["paths"].items()
    for method in item
)
# Cases per operation and backend. The inputs' breadth is the same on both backends; what only
# PostgreSQL refuses (a NUL byte in text, an integer beyond its column) is found in the first few
# dozen cases, so PostgreSQL gets fewer. The cases are drawn afresh each run (not derandomised),
# so successive runs cover new ones. At 200 and 50 this file took a fifth of `make test`'s time;
# at Hypothesis' default of 100 and 30, a tenth, which kept the suite over its fifteen minutes;
# at 60 and 30, 112 s of the two workers' time, and fresh clones' runs reached 15 min 39 s.
MAX_EXAMPLES = {"sqlite": 40, "postgresql": 20}


@dataclass
class Target:
    schema: schemathesis.BaseSchema
    url: str
    headers: dict[str, str]
    owned: dict[str, int]  # path parameter -> an id the key's organisation owns
    own_key_id: int  # the fuzzer's admin key, which it must not revoke


@pytest.fixture(scope="module")
def target(api_server: LiveServer) -> Iterator[Target]:
    org = Org.create(api_server)
    with clients(org) as (admin, ingest, _):
        sid = create_structure(admin, "fuzzed")["id"]
        model = train_fault_mode(admin, ingest, sid, "k2", seed=61)
        # One faulty or unknown verdict is enough to open an alarm for the fuzzer to act on.
        rules = {"rules": [{"kind": "persistence", "k": 1, "m": 1}]}
        assert admin.put(f"{API}/structures/{sid}/alarm-rules", json=rules).status_code == 200
        response = post_record(ingest, sid, json_body(2000), inspect="true")
        assert response.status_code == 201, response.text
        record = response.json()
        (alarm,) = admin.get(f"{API}/alarms", params={"structure_id": sid}).json()["items"]
        response = admin.post(f"{API}/structures/{sid}/models/baseline", json={"record_ids": [record["id"]]})
        assert response.status_code == 201, response.text
        body = {"record_id": record["id"], "base_model_id": response.json()["id"]}
        response = admin.post(f"{API}/structures/{sid}/refinements", json=body)
        assert response.status_code == 201, response.text
        refinement_id = response.json()["id"]
        schedule = {
            "action": "inspect_pending",
            "interval_seconds": 3600,
            "first_run_at": "2099-01-01T00:00:00Z",
        }
        response = admin.post(f"{API}/structures/{sid}/schedules", json=schedule)
        assert response.status_code == 201, response.text
        # The viewer key's id: revoking it leaves the fuzzer's admin key working.
        ids = {key["prefix"]: key["id"] for key in admin.get(f"{API}/keys").json()}
        key_id, own_key_id = (ids[org.keys[role].split("_")[1]] for role in ("viewer", "admin"))
    schema = schemathesis.openapi.from_url(f"{api_server.url}/openapi.json")
    owned = {
        "structure_id": sid,
        "model_id": model["id"],
        "record_id": record["id"],
        "verdict_id": record["verdict"]["id"],
        "refinement_id": refinement_id,
        "schedule_id": response.json()["id"],
        "key_id": key_id,
        "alarm_id": alarm["id"],
    }
    headers = {"Authorization": f"Bearer {org.keys['admin']}"}
    yield Target(schema, api_server.url, headers, owned, own_key_id)
    # The fuzzer's schedules would go on running (every 10 s at the most) for the tests after:
    # removed with the fuzzer's own key, which must still work. Had the fuzzer revoked it (it drew
    # that key's id once, as it draws any other), every operation fuzzed after would have met a
    # 401 and reached nothing behind it.
    with api_server.client(org.keys["admin"]) as admin:
        assert admin.get(f"{API}/keys").status_code == 200
        listed = admin.get(f"{API}/structures/{sid}/schedules")
        assert listed.status_code == 200, listed.text
        for created in listed.json():
            assert admin.delete(f"{API}/structures/{sid}/schedules/{created['id']}").status_code == 204


def test_the_served_schema_has_every_operation(target: Target):
    served = sorted(
        (method.upper(), path) for path, item in target.schema.raw_schema["paths"].items() for method in item
    )
    assert served == OPERATIONS
    assert sum(path.startswith(API) for _, path in OPERATIONS) == 43
    assert {(method, path) for method, path in OPERATIONS if not path.startswith(API)} == {
        ("GET", "/healthz"),
        ("GET", "/readyz"),
        ("GET", "/metrics"),
    }


@pytest.mark.parametrize(("method", "path"), OPERATIONS, ids=[f"{m} {p}" for m, p in OPERATIONS])
def test_no_server_error(target: Target, method: str, path: str, request: pytest.FixtureRequest):
    operation = target.schema[path][method]
    owned = {name: value for name, value in target.owned.items() if "{" + name + "}" in path}
    strategy = st.one_of(
        [
            operation.as_strategy(mode, path_parameters=fixed)
            for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE)
            for fixed in ([None, owned] if owned else [None])
        ]
    ).filter(lambda case: (case.path_parameters or {}).get("key_id") != target.own_key_id)

    @settings(
        max_examples=MAX_EXAMPLES[request.node.callspec.params["api_server"]],
        deadline=None,
        database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much, HealthCheck.data_too_large],
    )
    @given(case=strategy)
    def no_server_error(case) -> None:
        case.call_and_validate(base_url=target.url, headers=target.headers, checks=[not_a_server_error])

    no_server_error()
