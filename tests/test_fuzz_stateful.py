"""A stateful fuzz run over every route with two organisations.

Two organisations, each with an admin, an ingest and a viewer key, a trained structure, records,
verdicts, a baseline, a refinement and a schedule, are driven by a Hypothesis state machine over
HTTP against the live server. Its steps mix the organisations and every kind of request: each
OpenAPI operation as Schemathesis generates it (valid and invalid, with the organisation's own
ids in the path or random ones), the dashboard's pages and forms, valid uploads, trainings,
activations, refinements and schedules made by hand, uploads of records that would make the
statistics overflow, and the ids one organisation created requested with the other's keys.

What must hold on every answer, whatever came before:

- no server error (5xx) and no dropped connection;
- every JSON answer, and the charts' JSON in every dashboard page, is standard JSON (no ``NaN``
  or ``Infinity``: browsers cannot read them);
- an id created by one organisation, asked for with the other's key, is a 404 (a 404 or 422 when
  it is named in a body), never data; no listing shows the other organisation's objects; the
  dashboard shows its own objects and never the other's names;
- a record with NaN, ±inf, a JSON number that overflows (1e400), y scaled by 1e60, x by 1e200
  or a constant signal is refused with a 4xx, whatever the encoding (JSON, CSV, NPZ) and the
  ``inspect`` mode, and the number of stored records does not change.

First every operation of the served schema is fuzzed with each organisation's admin key, valid
and invalid cases with its own ids or random ones (key-management routes, which may revoke the
key they are sent with, with a third organisation's), so that every route is reached whatever the
state machine chooses; each run of
the state machine then starts with a tour (each overflowing input, each kind of foreign id, the
own listings and each page once) before its steps. Routes outside the schema are listed in
``OTHER_ROUTES``: a new one must be added there.

Violations are collected over the whole run, not raised at the first, so one run lists every
kind of failure (deduplicated by property, route and status, each with one request that shows
it); the test fails when the list is not empty, or when a route was never exercised. The run
is derandomised (the same steps every time); ``NARXWATCH_FUZZ_EXAMPLES``, ``NARXWATCH_FUZZ_STEPS``
and ``NARXWATCH_FUZZ_SWEEP_EXAMPLES`` lengthen it.
"""

from __future__ import annotations

import functools
import json
import os
import re
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import httpx
import numpy as np
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.stateful import (
    RuleBasedStateMachine,
    initialize,
    invariant,
    rule,
    run_state_machine_as_test,
)
from schemathesis import GenerationMode
from sqlalchemy import text

from harness.api_helpers import (
    API,
    FS,
    RIG_TERMS,
    create_structure,
    csv_text,
    experiments,
    json_body,
    noise,
    npz_bytes,
    post_record,
    raw_json,
)
from harness.live import LiveServer, http_client
from service.security import Role

# The run is on SQLite: what it looks for (server errors, non-standard JSON, one organisation's
# data shown to the other, overflowing records stored) is the service's, whichever database is
# under it. What only PostgreSQL refuses (a NUL byte in text, an integer beyond its column) has a
# test of its own below, on PostgreSQL, which sends it to every operation. Every run's tour sends
# each overflowing input, each kind of foreign id and each page with a query: more runs and steps
# vary the state those meet, not what is sent. What the run has caught (a refinement read across
# organisations, a record's magnitude check dropped) the tours caught, and ids unbounded above the
# sweep: two short runs keep both tours.
EXAMPLES = int(os.environ.get("NARXWATCH_FUZZ_EXAMPLES", "2"))  # runs of the state machine
STEPS = int(os.environ.get("NARXWATCH_FUZZ_STEPS", "20"))
# Cases per operation and organisation in the sweep, which is the fuzzing of the served schema:
# each operation, valid and invalid, with the organisation's own ids and with random ones (random
# ids mostly reach a 404; own ones reach the filters, parsers and training behind it).
SWEEP_EXAMPLES = int(os.environ.get("NARXWATCH_FUZZ_SWEEP_EXAMPLES", "10"))

# The routes outside the OpenAPI schema (the dashboard and FastAPI's documentation pages).
DASHBOARD_PAGES = (
    "/dashboard",
    "/dashboard/structures/{structure_id}",
    "/dashboard/records/{record_id}",
    "/dashboard/refinements/{refinement_id}",
)
OTHER_ROUTES = {
    ("GET", "/dashboard/login"),
    ("POST", "/dashboard/login"),
    ("POST", "/dashboard/logout"),
    ("GET", "/dashboard/static/plotly.min.js"),
    ("GET", "/openapi.json"),
    ("GET", "/docs"),
    ("GET", "/docs/static/swagger-ui-bundle.js"),
    ("GET", "/"),
} | {("GET", page) for page in DASHBOARD_PAGES}
CHARTS = re.compile(rb'<script type="application/json"[^>]*>(.*?)</script>', re.DOTALL)
OTHER_PAGES = sorted(route for method, route in OTHER_ROUTES if method == "GET")
FAR_FUTURE = "2099-01-01T00:00:00Z"
# Kinds of object an organisation creates, named as the path parameters that take their ids.
R = f"{API}/structures/{{structure_id}}"
KINDS = ("structure_id", "record_id", "model_id", "verdict_id", "refinement_id", "schedule_id")


# --- the world: two organisations on one server, what each owns, what went wrong ------------


@dataclass
class Organisation:
    name: str
    keys: dict[str, str]
    cookie: str
    # kind -> {id: the structure it belongs to}
    owned: dict[str, dict[int, int]] = field(default_factory=lambda: {kind: {} for kind in KINDS})
    # Structure names this run chose, unlike any other text on a page, to find leaks in HTML.
    names: set[str] = field(default_factory=set)
    baselines: set[int] = field(default_factory=set)  # the model ids that are baselines (refinable)

    def own(self, kind: str, object_id: int, structure_id: int) -> None:
        self.owned[kind][object_id] = structure_id

    def ids(self, kind: str, structure_id: int | None = None) -> list[int]:
        return sorted(i for i, s in self.owned[kind].items() if structure_id is None or s == structure_id)


@dataclass
class Violation:
    count: int
    example: str


class World:
    """The live server, the two organisations (and one whose keys the key routes may revoke),
    persistent clients, and every violation and route seen."""

    def __init__(self, server: LiveServer) -> None:
        self.server = server
        self.schema = schemathesis.openapi.from_url(f"{server.url}/openapi.json", timeout=120)
        self.operations = sorted(
            (method.upper(), path)
            for path, item in self.schema.raw_schema["paths"].items()
            for method in item
            if method in {"get", "post", "put", "patch", "delete"}
        )
        self.http = http_client(base_url=server.url, timeout=120)
        self.orgs = (self._organisation("a"), self._organisation("b"))
        self.keyholder = self._organisation("k")
        self.violations: dict[tuple[str, str, str], Violation] = {}
        self.covered: set[tuple[str, str]] = set()
        self.requests = 0
        self.runs = self.steps = 0
        self.previous = "none"  # the request before, named when a connection drops

    def _organisation(self, tag: str) -> Organisation:
        name = f"fuzz-{tag}-{uuid.uuid4().hex[:8]}"
        keys = {role.name: self.server.key(role, name) for role in Role}
        response = self.http.post(
            "/dashboard/login", data={"api_key": keys["viewer"]}, headers={"Origin": self.server.url}
        )
        assert response.status_code == 303, response.text
        token = response.cookies["narxwatch_session"]
        self.http.cookies.clear()  # each request names its login itself
        return Organisation(name, keys, token)

    def organisations_for(self, path: str) -> tuple[Organisation, ...]:
        """Key routes may revoke the key they are sent with: they get an organisation of their own."""
        return (self.keyholder,) if "/keys" in path else self.orgs

    def other(self, org: Organisation) -> Organisation:
        return self.orgs[1] if org is self.orgs[0] else self.orgs[0]

    # --- requests and the checks every answer goes through --------------------------------

    def send(
        self,
        org: Organisation,
        role: str,
        method: str,
        route: str,
        ids: dict[str, Any] | None = None,
        **kwargs: Any,
    ) -> httpx.Response | None:
        """``method route`` (a template, ``{name}`` filled from ``ids``) as ``org``'s ``role``
        key, or its dashboard login for dashboard pages; None when the connection failed."""
        path = route.format(**(ids or {}))
        headers = dict(kwargs.pop("headers", {}))
        if route.startswith("/dashboard"):
            headers["Cookie"] = f"narxwatch_session={org.cookie}"
        else:
            headers["Authorization"] = f"Bearer {org.keys[role]}"
        self.covered.add((method, route))
        self.requests += 1
        described = f"{method} {path} as {org.name}'s {role}"
        try:
            response = self.http.request(method, path, headers=headers, **kwargs)
        except httpx.TransportError as exc:
            self.violate(
                "connection dropped", method, route, "", f"{described}: {exc!r} (before it: {self.previous})"
            )
            self.http.close()
            self.http = http_client(base_url=self.server.url, timeout=120)
            return None
        self.previous = f"{described} → {response.status_code}"
        self.check_answer(
            method,
            route,
            response.status_code,
            response.headers.get("content-type", ""),
            response.content,
            lambda: f"{described}: {_body_of(kwargs)} → {response.status_code} {response.text[:300]}",
        )
        return response

    def check_answer(
        self,
        method: str,
        route: str,
        status: int,
        content_type: str,
        content: bytes,
        describe: Callable[[], str],
    ) -> None:
        if status >= 500:
            self.violate("server error", method, route, str(status), describe())
        documents = []
        if content_type.startswith("application/json") and content:
            documents.append(content)
        elif content_type.startswith("text/html"):
            # The dashboard's charts: JSON.parse in the browser takes standard JSON only.
            documents += [m.group(1) for m in CHARTS.finditer(content)]
        for document in documents:
            try:
                json.loads(document, parse_constant=_refuse_constant)
            except ValueError as exc:
                self.violate("not standard JSON", method, route, str(status), f"{describe()} ({exc})")

    def violate(self, what: str, method: str, route: str, status: str, example: str) -> None:
        key = (what, f"{method} {route}", status)
        if key in self.violations:
            self.violations[key].count += 1
        else:
            self.violations[key] = Violation(1, example[:1200])

    def expect(self, ok: bool, what: str, method: str, route: str, response: httpx.Response | None, why: str):
        if response is not None and not ok:
            self.violate(what, method, route, str(response.status_code), f"{why}: {response.text[:300]}")

    def call_case(self, org: Organisation, role: str, case: Any) -> None:
        """Send a Schemathesis case as ``org``'s ``role`` key, check the answer, note what it created."""
        method, path = case.method.upper(), case.path
        headers = {"Authorization": f"Bearer {org.keys[role]}"}
        self.covered.add((method, path))
        self.requests += 1
        curl = case.as_curl_command(headers, base_url=self.server.url)[:600]
        try:
            response = case.call(base_url=self.server.url, headers=headers, timeout=120)
        except Exception as exc:  # requests' connection errors, whatever the transport raised
            self.violate("connection dropped", method, path, "", f"{curl}: {exc!r}")
            return
        self.check_answer(
            method,
            path,
            response.status_code,
            (response.headers.get("content-type") or [""])[0],
            response.content,
            lambda: f"{curl} → {response.status_code} {response.content[:300]!r}",
        )
        if org is not self.keyholder and 200 <= response.status_code < 300 and method == "POST":
            request = httpx.Request(method, f"{self.server.url}{case.formatted_path}")
            self.register(org, method, path, httpx.Response(200, content=response.content, request=request))

    def records_stored(self) -> int:
        with self.server.app.state.engine.connect() as connection:
            return connection.execute(text("SELECT count(*) FROM records")).scalar_one()

    # --- what a successful answer created -------------------------------------------------

    def register(self, org: Organisation, method: str, route: str, response: httpx.Response | None) -> None:
        """Note the ids an answer shows as created, so later steps can use and probe them."""
        if response is None or not 200 <= response.status_code < 300 or method != "POST":
            return
        try:
            body = response.json()
        except ValueError:
            return
        if not isinstance(body, dict) or not isinstance(body.get("id"), int):
            return
        if route == f"{API}/structures":
            org.own("structure_id", body["id"], body["id"])
        elif route.endswith("/records") and "structure_id" in body:
            org.own("record_id", body["id"], body["structure_id"])
            if isinstance(body.get("verdict"), dict):
                org.own("verdict_id", body["verdict"]["id"], body["structure_id"])
        elif route.endswith("/inspect") and "structure_id" in body:
            org.own("verdict_id", body["id"], body["structure_id"])
        elif route.endswith(("/models/baseline", "/models/fault-modes")) and "kind" in body:
            org.own("model_id", body["id"], _structure_of(response))
            if body["kind"] == "baseline":
                org.baselines.add(body["id"])
        elif route.endswith("/refinements") and "structure_id" in body:
            org.own("refinement_id", body["id"], body["structure_id"])
            if isinstance(body.get("refined_model"), dict):
                org.own("model_id", body["refined_model"]["id"], body["structure_id"])
                org.baselines.add(body["refined_model"]["id"])
        elif route.endswith("/schedules") and "action" in body:
            org.own("schedule_id", body["id"], _structure_of(response))

    def report(self) -> str:
        lines = [
            f"{len(self.violations)} kinds of violation in {self.requests} requests "
            f"({self.runs} runs of {self.steps} steps in all):"
        ]
        for (what, route, status), violation in sorted(self.violations.items()):
            lines.append(
                f"- {what}: {route} → {status or '—'} ({violation.count}×), e.g. {violation.example}"
            )
        return "\n".join(lines)


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not JSON")


def _body_of(kwargs: dict[str, Any]) -> str:
    if "json" in kwargs:
        return json.dumps(kwargs["json"])[:300]
    content = kwargs.get("content")
    return f"{len(content)}-byte body" if content is not None else ""


def _structure_of(response: httpx.Response) -> int:
    return int(re.search(r"/structures/(\d+)/", response.request.url.path).group(1))  # type: ignore[union-attr]


# --- the seeded organisations -----------------------------------------------------------------


def seed(world: World, org: Organisation, seed_value: int) -> None:
    """A trained structure with records, a verdict, a baseline, a refinement and a schedule."""
    headers = {"Authorization": f"Bearer {org.keys['admin']}"}
    with http_client(base_url=world.server.url, headers=headers, timeout=120) as admin:
        name = f"{org.name}-rig"
        structure = create_structure(admin, name)
        sid = structure["id"]
        org.names.add(name)
        org.own("structure_id", sid, sid)
        runs = experiments(admin, sid, "k2", seed_value)
        for run in runs:
            org.own("record_id", run["record_id"], sid)
        body = {"name": "k2", "k_min": -32.0, "k_max": 32.0, "experiments": runs, "terms": RIG_TERMS}
        response = admin.post(f"{API}/structures/{sid}/models/fault-modes", json=body)
        assert response.status_code == 201, response.text
        world.register(org, "POST", f"{R}/models/fault-modes", response)
        response = post_record(admin, sid, json_body(2000), inspect="true")
        assert response.status_code == 201, response.text
        world.register(org, "POST", f"{R}/records", response)
        record_id = max(org.ids("record_id", sid))
        response = admin.post(
            f"{API}/structures/{sid}/models/baseline", json={"record_ids": [record_id], "terms": RIG_TERMS}
        )
        assert response.status_code == 201, response.text
        world.register(org, "POST", f"{R}/models/baseline", response)
        refinement = {"record_id": record_id, "base_model_id": response.json()["id"]}
        response = admin.post(f"{API}/structures/{sid}/refinements", json=refinement)
        assert response.status_code == 201, response.text
        world.register(org, "POST", f"{R}/refinements", response)
        schedule = {"action": "inspect_pending", "interval_seconds": 3600, "first_run_at": FAR_FUTURE}
        response = admin.post(f"{API}/structures/{sid}/schedules", json=schedule)
        assert response.status_code == 201, response.text
        world.register(org, "POST", f"{R}/schedules", response)


@pytest.fixture(scope="module")
def world(sqlite_api_server: LiveServer):
    world = World(sqlite_api_server)
    for i, org in enumerate(world.orgs):
        seed(world, org, 71 + i)
    yield world
    # The fuzzer's schedules would go on running for the tests after this one.
    for org in (*world.orgs, world.keyholder):
        for sid in org.ids("structure_id"):
            listed = world.send(org, "admin", "GET", f"{API}/structures/{{sid}}/schedules", {"sid": sid})
            for schedule in listed.json() if listed is not None and listed.status_code == 200 else []:
                world.send(
                    org,
                    "admin",
                    "DELETE",
                    f"{API}/structures/{{sid}}/schedules/{{id}}",
                    {"sid": sid, "id": schedule["id"]},
                )
    world.http.close()


# --- inputs that would make the statistics overflow or divide by zero ------------------------

OVERFLOW_TOKEN = 4096.5  # replaced by the literal 1e400 in the text of a JSON or CSV body


def poisoned(kind: str, n: int, seed_value: int) -> tuple[np.ndarray, np.ndarray, float]:
    x, y = noise(n, seed_value)
    at = n // 2
    fs = FS
    match kind:
        case "NaN in x":
            x[at] = np.nan
        case "NaN in y":
            y[at] = np.nan
        case "+inf in x":
            x[at] = np.inf
        case "-inf in y":
            y[at] = -np.inf
        case "1e400 in y" | "1e400 in x":
            (y if kind.endswith("y") else x)[at] = OVERFLOW_TOKEN
        case "y × 1e60":
            y = y * 1e60
        case "x × 1e200":
            x = x * 1e200
        case "constant x":
            x = np.full(n, 1.0)
        case "constant y":
            y = np.zeros(n)
        case "NaN fs":
            fs = float("nan")
        case _:
            raise ValueError(kind)
    return x, y, fs


POISONS = (
    "NaN in x",
    "NaN in y",
    "+inf in x",
    "-inf in y",
    "1e400 in y",
    "1e400 in x",
    "y × 1e60",
    "x × 1e200",
    "constant x",
    "constant y",
    "NaN fs",
)


def encode(encoding: str, x: np.ndarray, y: np.ndarray, fs: float) -> tuple[bytes, str]:
    token = repr(OVERFLOW_TOKEN)
    if encoding == "json":
        body = raw_json({"x": x.tolist(), "y": y.tolist(), "fs": fs}).decode()
        return body.replace(token, "1e400").encode(), "application/json"
    if encoding == "csv":
        return csv_text(x, y, fs).replace(token, "1e400").encode(), "text/csv"
    overflowed = [np.where(a == OVERFLOW_TOKEN, np.inf, a) for a in (x, y)]
    return npz_bytes(x=overflowed[0], y=overflowed[1], fs=np.float64(fs)), "application/x-npz"


# --- the state machine ------------------------------------------------------------------------
#
# What a step draws never depends on what earlier steps created (Hypothesis replays choice
# sequences and insists that a replay draws the same kinds of value): an object is chosen by
# drawing an index, taken modulo the number of objects there are at that moment.


def _train_baseline_on(record_id: int) -> dict[str, Any]:
    return {"json": {"record_ids": [record_id], "terms": RIG_TERMS}}


def _train_mode_on(record_id: int, other_record: int) -> dict[str, Any]:
    runs = [{"record_id": record_id, "k": -10.0}, {"record_id": other_record, "k": 10.0}]
    return {"json": {"name": "k9", "k_min": -32.0, "k_max": 32.0, "experiments": runs, "terms": RIG_TERMS}}


def _refine(record_id: int, model_id: int) -> dict[str, Any]:
    return {"json": {"record_id": record_id, "base_model_id": model_id}}


# Requests that take an id of each kind in their path: (role, method, route, keyword arguments).
PATH_PROBES: dict[str, list[tuple[str, str, str, dict[str, Any]]]] = {
    "structure_id": [
        ("viewer", "GET", R, {}),
        ("viewer", "GET", f"{R}/verdicts", {}),
        ("viewer", "GET", f"{R}/summary", {}),
        ("viewer", "GET", f"{R}/models", {}),
        ("viewer", "GET", f"{R}/refinements", {}),
        ("viewer", "GET", f"{R}/schedules", {}),
        ("viewer", "GET", "/dashboard/structures/{structure_id}", {}),
        (
            "ingest",
            "POST",
            f"{R}/records",
            {"content": raw_json(json_body(300, seed=5)), "headers": {"Content-Type": "application/json"}},
        ),
        (
            "admin",
            "POST",
            f"{R}/schedules",
            {"json": {"action": "inspect_pending", "interval_seconds": 3600, "first_run_at": FAR_FUTURE}},
        ),
    ],
    "record_id": [
        ("ingest", "POST", f"{API}/records/{{record_id}}/inspect", {}),
        ("viewer", "GET", "/dashboard/records/{record_id}", {}),
    ],
    "verdict_id": [("viewer", "GET", f"{API}/verdicts/{{verdict_id}}", {})],
    "refinement_id": [
        ("viewer", "GET", f"{API}/refinements/{{refinement_id}}", {}),
        ("viewer", "GET", "/dashboard/refinements/{refinement_id}", {}),
    ],
}
INDEX = st.integers(0, 2**16)
# A page's query: its filters and cursor, each with any text.
QUERY = st.dictionaries(
    st.sampled_from(["status", "fault_mode", "start", "end", "cursor", "mode", "next"]),
    st.text(max_size=30),
    max_size=3,
)
ENCODINGS = ("json", "csv", "npz")
INSPECT_MODES = ("false", "true", "queue")


def _nth(ids: list[int], index: int) -> int | None:
    return ids[index % len(ids)] if ids else None


class FuzzMachine(RuleBasedStateMachine):
    world: World  # set by the test

    def __init__(self) -> None:
        super().__init__()
        self.w = self.world
        self.w.runs += 1

    @invariant()
    def count_steps(self) -> None:
        self.w.steps += 1

    @initialize(data=st.data(), encodings=st.lists(INDEX, min_size=len(POISONS), max_size=len(POISONS)))
    def tour(self, data: st.DataObject, encodings: list[int]) -> None:
        """Every run starts with each overflowing input, each kind of foreign id, the own
        readings and each page once, with a query of its own (Hypothesis' choice of rules favours
        some rules over others): the steps after it vary them."""
        for kind, index in zip(POISONS, encodings, strict=True):
            self.upload_overflowing(
                data, kind, ENCODINGS[index % 3], INSPECT_MODES[index // 3 % 3], seed_value=index
            )
        for kind in KINDS:
            self.cross_tenant(data, kind)
        self.read_own(data)
        for route in OTHER_PAGES:
            query = data.draw(QUERY, label="query")
            self.other_page(data, route, data.draw(INDEX, label="index"), query)

    def _org(self, data: st.DataObject) -> Organisation:
        return data.draw(st.sampled_from(self.w.orgs), label="organisation")

    def _choose(self, data: st.DataObject, ids: list[int], label: str) -> int | None:
        return _nth(ids, data.draw(INDEX, label=label))

    def _structure_with(self, data: st.DataObject, org: Organisation, kind: str) -> int | None:
        return self._choose(data, sorted(set(org.owned[kind].values())), f"structure with a {kind}")

    # --- every OpenAPI operation, as Schemathesis generates it --------------------------------

    @rule(
        data=st.data(),
        operation=INDEX,
        role=st.sampled_from(["admin", "ingest", "viewer"]),
        mode=st.sampled_from([GenerationMode.POSITIVE, GenerationMode.NEGATIVE]),
        owned_ids=st.booleans(),
        index=INDEX,
    )
    def schemathesis_case(
        self,
        data: st.DataObject,
        operation: int,
        role: str,
        mode: GenerationMode,
        owned_ids: bool,
        index: int,
    ) -> None:
        method, path = self.w.operations[operation % len(self.w.operations)]
        org = self.w.organisations_for(path)[index % 2 if "/keys" not in path else 0]
        case = data.draw(self.w.schema[path][method.lower()].as_strategy(mode), label="case")
        if owned_ids:
            case.path_parameters = {**(case.path_parameters or {}), **self.owned_ids(org, path, index)}
        self.w.call_case(org, role, case)

    @staticmethod
    def owned_ids(org: Organisation, path: str, index: int) -> dict[str, int]:
        """The path's ids taken from what ``org`` owns, of one structure where the path has one."""
        names = [name for name in re.findall(r"{(\w+)}", path) if name in KINDS]
        fixed: dict[str, int] = {}
        if "structure_id" in names:
            others = [name for name in names if name != "structure_id"]
            candidates = sorted(set(org.owned[others[0]].values()) if others else org.owned["structure_id"])
            sid = _nth(candidates, index)
            if sid is None:
                return {}
            fixed["structure_id"] = sid
            for name in others:
                fixed[name] = _nth(org.ids(name, sid), index)  # type: ignore[assignment]
        else:
            for name in names:
                if (chosen := _nth(org.ids(name), index)) is not None:
                    fixed[name] = chosen
        return fixed

    # --- valid work, so that the state grows ------------------------------------------------

    @rule(
        data=st.data(),
        n=st.sampled_from([250, 600, 2000]),
        encoding=st.sampled_from(ENCODINGS),
        inspect=st.sampled_from(INSPECT_MODES),
        seed_value=st.integers(0, 2**31),
    )
    def upload(self, data: st.DataObject, n: int, encoding: str, inspect: str, seed_value: int) -> None:
        org = self._org(data)
        sid = self._choose(data, org.ids("structure_id"), "structure")
        body, media = encode(encoding, *noise(n, seed_value), FS)
        route = f"{R}/records"
        response = self.w.send(
            org,
            "ingest",
            "POST",
            route,
            {"structure_id": sid},
            content=body,
            headers={"Content-Type": media},
            params={"inspect": inspect},
        )
        self.w.register(org, "POST", route, response)

    @rule(
        data=st.data(),
        indices=st.lists(INDEX, min_size=1, max_size=3),
        baseline=st.booleans(),
        k=st.floats(-30, 30),
        mode=st.sampled_from(["k1", "k2", "k3"]),
    )
    def train(self, data: st.DataObject, indices: list[int], baseline: bool, k: float, mode: str) -> None:
        org = self._org(data)
        sid = self._structure_with(data, org, "record_id")
        records = org.ids("record_id", sid)
        chosen = [_nth(records, index) for index in indices]
        if baseline:
            route, body = f"{R}/models/baseline", {"record_ids": chosen, "terms": RIG_TERMS}
        else:
            runs = [{"record_id": r, "k": k * (i - 1)} for i, r in enumerate(chosen)]
            route, body = (
                f"{R}/models/fault-modes",
                {"name": mode, "k_min": -32.0, "k_max": 32.0, "terms": RIG_TERMS},
            )
            body["experiments"] = runs
        response = self.w.send(org, "admin", "POST", route, {"structure_id": sid}, json=body)
        self.w.register(org, "POST", route, response)

    @rule(data=st.data(), index=INDEX)
    def activate(self, data: st.DataObject, index: int) -> None:
        org = self._org(data)
        sid = self._structure_with(data, org, "model_id")
        params = {"structure_id": sid, "model_id": _nth(org.ids("model_id", sid), index)}
        self.w.send(org, "admin", "POST", f"{R}/models/{{model_id}}/activate", params)

    @rule(data=st.data())
    def inspect(self, data: st.DataObject) -> None:
        org = self._org(data)
        route = f"{API}/records/{{record_id}}/inspect"
        record_id = self._choose(data, org.ids("record_id"), "record")
        self.w.register(
            org, "POST", route, self.w.send(org, "ingest", "POST", route, {"record_id": record_id})
        )

    @rule(data=st.data(), index=INDEX)
    def refine(self, data: st.DataObject, index: int) -> None:
        org = self._org(data)
        sid = self._structure_with(data, org, "model_id")
        baselines = sorted(set(org.ids("model_id", sid)) & org.baselines)
        records = org.ids("record_id", sid)
        if baselines and records:
            route = f"{R}/refinements"
            body = _refine(_nth(records, index), _nth(baselines, index))  # type: ignore[arg-type]
            response = self.w.send(org, "admin", "POST", route, {"structure_id": sid}, **body)
            self.w.register(org, "POST", route, response)

    @rule(data=st.data(), name=st.text(min_size=1, max_size=20), fs=st.floats(1, 1e5))
    def create_structure(self, data: st.DataObject, name: str, fs: float) -> None:
        org = self._org(data)
        tagged = f"{org.name}-{uuid.uuid4().hex[:6]}-{name}"
        route = f"{API}/structures"
        response = self.w.send(org, "admin", "POST", route, json={"name": tagged, "fs": fs})
        self.w.register(org, "POST", route, response)
        if response is not None and response.status_code == 201:
            org.names.add(tagged)

    @rule(data=st.data(), action=st.sampled_from(["inspect_pending", "reinspect_latest"]))
    def schedule(self, data: st.DataObject, action: str) -> None:
        org = self._org(data)
        sid = self._choose(data, org.ids("structure_id"), "structure")
        body = {"action": action, "interval_seconds": 3600, "first_run_at": FAR_FUTURE}
        route = f"{R}/schedules"
        response = self.w.send(org, "admin", "POST", route, {"structure_id": sid}, json=body)
        self.w.register(org, "POST", route, response)

    @rule(data=st.data())
    def delete_schedule(self, data: st.DataObject) -> None:
        org = self._org(data)
        schedule_id = self._choose(data, org.ids("schedule_id"), "schedule")
        if schedule_id is None:
            return
        params = {"structure_id": org.owned["schedule_id"][schedule_id], "schedule_id": schedule_id}
        response = self.w.send(org, "admin", "DELETE", f"{R}/schedules/{{schedule_id}}", params)
        if response is not None and response.status_code in (204, 404):
            del org.owned["schedule_id"][schedule_id]

    # --- records that would make the statistics overflow -------------------------------------

    @rule(
        data=st.data(),
        kind=st.sampled_from(POISONS),
        encoding=st.sampled_from(ENCODINGS),
        inspect=st.sampled_from(INSPECT_MODES),
        seed_value=st.integers(0, 2**31),
    )
    def upload_overflowing(
        self, data: st.DataObject, kind: str, encoding: str, inspect: str, seed_value: int
    ) -> None:
        org = self._org(data)
        sid = self._choose(data, org.ids("structure_id"), "structure")
        body, media = encode(encoding, *poisoned(kind, 2000, seed_value))
        before = self.w.records_stored()
        route = f"{R}/records"
        response = self.w.send(
            org,
            "ingest",
            "POST",
            route,
            {"structure_id": sid},
            content=body,
            headers={"Content-Type": media},
            params={"inspect": inspect},
        )
        stored = self.w.records_stored() - before
        self.w.register(org, "POST", route, response)
        why = f"{kind} as {encoding} with inspect={inspect}"
        refused = response is None or 400 <= response.status_code < 500
        self.w.expect(refused, f"not refused: {kind}", "POST", route, response, why)
        if stored:
            self.w.violate(f"stored: {kind}", "POST", route, "", f"{stored} record(s) stored by {why}")

    # --- one organisation's ids with the other's keys ----------------------------------------

    @rule(data=st.data(), kind=st.sampled_from(KINDS))
    def cross_tenant(self, data: st.DataObject, kind: str) -> None:
        owner = self._org(data)
        intruder = self.w.other(owner)
        foreign = self._choose(data, owner.ids(kind), kind)
        if foreign is None:
            return
        foreign_sid = owner.owned[kind][foreign]
        # The intruder's seeded structure: it has records, a baseline and a fault mode.
        own_sid = min(intruder.owned["structure_id"])
        own_record = max(intruder.ids("record_id", own_sid))
        own_model = min(set(intruder.ids("model_id", own_sid)) & intruder.baselines)
        for role, method, route, kwargs in PATH_PROBES.get(kind, []):
            self._refused(intruder, role, method, route, {kind: foreign}, kwargs, (404,))
        by_body: list[tuple[str, int, dict[str, Any]]] = []  # route, structure in the path, body
        if kind == "record_id":
            by_body += [
                (f"{R}/models/baseline", own_sid, _train_baseline_on(foreign)),
                (f"{R}/models/fault-modes", own_sid, _train_mode_on(foreign, own_record)),
                (f"{R}/refinements", own_sid, _refine(foreign, own_model)),
            ]
        elif kind == "model_id":
            by_body.append((f"{R}/refinements", own_sid, _refine(own_record, foreign)))
            # In the path beside a structure of the intruder's own, and beside the owner's.
            for sid in (own_sid, foreign_sid):
                params = {"structure_id": sid, "model_id": foreign}
                self._refused(
                    intruder, "admin", "POST", f"{R}/models/{{model_id}}/activate", params, {}, (404,)
                )
        elif kind == "schedule_id":
            for sid in (own_sid, foreign_sid):
                params = {"structure_id": sid, "schedule_id": foreign}
                self._refused(
                    intruder, "admin", "DELETE", f"{R}/schedules/{{schedule_id}}", params, {}, (404,)
                )
        elif kind == "structure_id":
            # The owner's structure in the path, the intruder's own objects in the body.
            by_body += [
                (f"{R}/models/baseline", foreign, _train_baseline_on(own_record)),
                (f"{R}/models/fault-modes", foreign, _train_mode_on(own_record, own_record)),
                (f"{R}/refinements", foreign, _refine(own_record, own_model)),
            ]
        for route, sid, kwargs in by_body:
            self._refused(intruder, "admin", "POST", route, {"structure_id": sid}, kwargs, (404, 422))

    def _refused(
        self,
        org: Organisation,
        role: str,
        method: str,
        route: str,
        params: dict[str, int],
        kwargs: dict[str, Any],
        allowed: tuple[int, ...],
    ) -> None:
        response = self.w.send(org, role, method, route, params, **kwargs)
        if response is not None and response.status_code not in allowed:
            self.w.violate(
                "cross-tenant request not refused",
                method,
                route,
                str(response.status_code),
                f"{method} {route.format(**params)} by {org.name} (ids of the other organisation): "
                f"{_body_of(kwargs)} → {response.status_code} {response.text[:300]}",
            )
            self.w.register(org, method, route, response)

    # --- an organisation reads what it owns, and only that -----------------------------------

    @rule(data=st.data())
    def read_own(self, data: st.DataObject) -> None:
        org = self._org(data)
        other = self.w.other(org)
        sid = self._choose(data, org.ids("structure_id"), "structure")
        listed = self.w.send(org, "viewer", "GET", f"{API}/structures")
        if listed is not None and listed.status_code == 200:
            ids = {s["id"] for s in listed.json()}
            self._no_leak(org, ids, "structure_id", f"{API}/structures", listed)
            missing = set(org.owned["structure_id"]) - ids
            self.w.expect(
                not missing, "own structure not listed", "GET", f"{API}/structures", listed, str(missing)
            )
        for route, kind in (
            (f"{R}/models", "model_id"),
            (f"{R}/verdicts", "verdict_id"),
            (f"{R}/refinements", "refinement_id"),
            (f"{R}/schedules", "schedule_id"),
        ):
            query = {"limit": 1000} if kind == "verdict_id" else None
            response = self.w.send(org, "viewer", "GET", route, {"structure_id": sid}, params=query)
            own = response is None or response.status_code == 200
            self.w.expect(
                own, "own listing refused", "GET", route, response, f"structure {sid} of {org.name}"
            )
            if response is not None and response.status_code == 200:
                body = response.json()
                items = body["items"] if kind == "verdict_id" else body
                self._no_leak(org, {item["id"] for item in items}, kind, route, response)
        for route in (R, f"{R}/summary", "/dashboard/structures/{structure_id}"):
            response = self.w.send(org, "viewer", "GET", route, {"structure_id": sid})
            own = response is None or response.status_code == 200
            self.w.expect(own, "own object refused", "GET", route, response, f"structure {sid} of {org.name}")
        fleet = self.w.send(org, "viewer", "GET", "/dashboard")
        if fleet is not None:
            leaked = sorted(name for name in other.names if name in fleet.text)
            self.w.expect(not leaked, "cross-tenant read", "GET", "/dashboard", fleet, f"shows {leaked}")

    @rule(data=st.data(), kind=st.sampled_from(["record_id", "verdict_id", "refinement_id"]))
    def read_own_object(self, data: st.DataObject, kind: str) -> None:
        org = self._org(data)
        object_id = self._choose(data, org.ids(kind), kind)
        routes = {
            "record_id": ["/dashboard/records/{record_id}"],
            "verdict_id": [f"{API}/verdicts/{{verdict_id}}"],
            "refinement_id": [
                f"{API}/refinements/{{refinement_id}}",
                "/dashboard/refinements/{refinement_id}",
            ],
        }[kind]
        for route in routes if object_id is not None else []:
            response = self.w.send(org, "viewer", "GET", route, {kind: object_id})
            own = response is None or response.status_code == 200
            self.w.expect(
                own, "own object refused", "GET", route, response, f"{kind} {object_id} of {org.name}"
            )

    def _no_leak(
        self, org: Organisation, ids: set[int], kind: str, route: str, response: httpx.Response
    ) -> None:
        leaked = ids & set(self.w.other(org).owned[kind])
        self.w.expect(
            not leaked, "cross-tenant read", "GET", route, response, f"{org.name} sees {sorted(leaked)}"
        )

    # --- the routes outside the schema ------------------------------------------------------

    @rule(
        data=st.data(),
        route=st.sampled_from(OTHER_PAGES),
        index=INDEX,
        query=QUERY,
    )
    def other_page(self, data: st.DataObject, route: str, index: int, query: dict[str, str]) -> None:
        org = self._org(data)
        params = {name: _nth(org.ids(name), index) for name in re.findall(r"{(\w+)}", route)}
        if None not in params.values():
            self.w.send(org, "viewer", "GET", route, params, params=query)

    @rule(data=st.data(), api_key=st.text(max_size=60), next_page=st.text(max_size=60), valid=st.booleans())
    def login_and_out(self, data: st.DataObject, api_key: str, next_page: str, valid: bool) -> None:
        org = self._org(data)
        log_in_and_out(self.w, org, org.keys["viewer"] if valid else api_key, next_page)


def log_in_and_out(world: World, org: Organisation, key: str, next_page: str) -> None:
    """A dashboard login with ``key``, and where it opened a session, that session's logout."""
    origin = {"Origin": world.server.url}
    form = {"api_key": key, "next": next_page}
    response = world.send(org, "viewer", "POST", "/dashboard/login", data=form, headers=origin)
    token = response.cookies.get("narxwatch_session") if response is not None else None
    world.http.cookies.clear()
    if token:
        # Log this login out, never the organisation's own one the other steps use.
        world.send(
            Organisation(org.name, org.keys, token), "viewer", "POST", "/dashboard/logout", headers=origin
        )


def sweep(world: World, examples: int) -> None:
    """Each operation, valid and invalid, with each organisation's admin key and its own ids or
    random ones, ``examples`` cases each: every route is reached, whichever steps the state
    machine chooses. A key route keeps to the key holder's own ids: a random one could revoke the
    key it is sent with."""
    for method, path in world.operations:
        operation = world.schema[path][method.lower()]
        for org in world.organisations_for(path):
            owned = FuzzMachine.owned_ids(org, path, 0) or None
            ids = [owned] if owned is None or "key_id" in path else [owned, None]
            strategy = st.one_of(
                operation.as_strategy(mode, path_parameters=fixed)
                for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE)
                for fixed in ids
            )

            _each_case(strategy, examples, functools.partial(world.call_case, org, "admin"))
    # The dashboard's login and logout are outside the schema: each organisation's viewer logs in
    # and out once here, whether or not the state machine's steps draw a valid login.
    for org in world.orgs:
        log_in_and_out(world, org, org.keys["viewer"], "/dashboard")


def _each_case(strategy: st.SearchStrategy, examples: int, send: Callable[[Any], None]) -> None:
    """``send`` each of ``examples`` cases ``strategy`` draws, the same ones every run."""

    @settings(
        max_examples=examples,
        derandomize=True,
        database=None,
        deadline=None,
        suppress_health_check=list(HealthCheck),
    )
    @given(case=strategy)
    def each(case: Any) -> None:
        send(case)

    each()


def test_every_route_with_two_organisations(world: World):
    sweep(world, SWEEP_EXAMPLES)
    FuzzMachine.world = world
    run_state_machine_as_test(
        FuzzMachine,
        settings=settings(
            max_examples=EXAMPLES,
            stateful_step_count=STEPS,
            derandomize=True,
            database=None,
            deadline=None,
            suppress_health_check=list(HealthCheck),
        ),
    )
    never = sorted((set(world.operations) | OTHER_ROUTES) - world.covered)
    assert not world.violations and not never, (
        f"{world.report()}\nroutes never exercised (lengthen the run): {never}"
    )


# --- what only PostgreSQL refuses -------------------------------------------------------------

# Values PostgreSQL cannot store where SQLite takes anything: text with a NUL byte, integers
# beyond its 4- and 8-byte columns. Each replaces one string, or one integer, of a valid request's
# query, JSON body or text path parameter at a time (one value at a time: with every name bad, the
# first would be refused before the others reach the database); the path's ids stay the
# organisation's own, to reach what is behind them.
UNSTORABLE: dict[str, Callable[[Any], Any]] = {
    "NUL in text": lambda value: f"{value}\x00" if isinstance(value, str) else value,
    "2^31": lambda value: 2**31 if type(value) is int else value,
    "2^63": lambda value: 2**63 if type(value) is int else value,
}
UNSTORABLE_EXAMPLES = 3  # valid requests an operation, each sent once for every value replaced


def _leaves(value: Any, at: tuple[Any, ...] = ()) -> list[tuple[tuple[Any, ...], Any]]:
    """(where, value) of each value that is not a dict or a list."""
    if isinstance(value, dict):
        return [leaf for key, item in value.items() for leaf in _leaves(item, (*at, key))]
    if isinstance(value, list):
        return [leaf for index, item in enumerate(value) for leaf in _leaves(item, (*at, index))]
    return [(at, value)]


def _with(value: Any, at: tuple[Any, ...], new: Any) -> Any:
    """A copy of ``value`` with the value at ``at`` replaced by ``new``."""
    if not at:
        return new
    copied = dict(value) if isinstance(value, dict) else list(value)
    copied[at[0]] = _with(value[at[0]], at[1:], new)
    return copied


def _send_unstorable(world: World, org: Organisation, case: Any, *, change: Callable[[Any], Any]) -> None:
    """``case`` once for each of its values ``change`` replaces, that one replaced."""
    for part in ("query", "body", "path_parameters"):
        original = getattr(case, part)
        if not isinstance(original, dict | list):
            continue  # no such part, or a body that is not JSON (a record file)
        for at, value in _leaves(original):
            new = change(value)
            if new != value and (part != "path_parameters" or isinstance(value, str)):
                setattr(case, part, _with(original, at, new))
                world.call_case(org, "admin", case)
        setattr(case, part, original)


@pytest.fixture(scope="module")
def postgresql_world(postgresql_api_server: LiveServer):
    """Two organisations on PostgreSQL, each with a structure, a record and a schedule: what the
    operations' paths name without a training."""
    world = World(postgresql_api_server)
    for org in world.orgs:
        headers = {"Authorization": f"Bearer {org.keys['admin']}"}
        with http_client(base_url=world.server.url, headers=headers, timeout=120) as admin:
            sid = create_structure(admin, f"{org.name}-rig")["id"]
            org.own("structure_id", sid, sid)
            world.register(org, "POST", f"{R}/records", post_record(admin, sid, json_body(2000)))
            schedule = {"action": "inspect_pending", "interval_seconds": 3600, "first_run_at": FAR_FUTURE}
            response = admin.post(f"{API}/structures/{sid}/schedules", json=schedule)
            world.register(org, "POST", f"{R}/schedules", response)
    yield world
    world.http.close()


@pytest.mark.parametrize("unstorable", UNSTORABLE.values(), ids=UNSTORABLE.keys())
def test_values_postgresql_cannot_store_are_refused_by_every_operation(
    postgresql_world: World, unstorable: Callable[[Any], Any]
):
    """No server error and standard JSON from any operation, whatever text or integer it is sent."""
    world = postgresql_world
    world.violations.clear()
    for method, path in world.operations:
        operation = world.schema[path][method.lower()]
        org = world.organisations_for(path)[0]
        owned = FuzzMachine.owned_ids(org, path, 0) or None
        strategy = operation.as_strategy(GenerationMode.POSITIVE, path_parameters=owned)
        _each_case(
            strategy, UNSTORABLE_EXAMPLES, functools.partial(_send_unstorable, world, org, change=unstorable)
        )
    assert not world.violations, world.report()
