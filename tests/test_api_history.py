"""Fault history, summary and model versions through HTTP.

A structure with k1 and k2 fault-mode models gets ten inspected records whose acquisition times
are uploaded out of order (two share a time; one is given in +02:00); the history must list them
newest first, filter and paginate them, and the summary must agree with it.

On SQLite; what the database decides (the times it stores, and the order, time ranges and pages
it reads them in) on PostgreSQL too: the tests that take ``database_history``, and readiness.
"""

from __future__ import annotations

import base64
import datetime as dt
from dataclasses import dataclass

import numpy as np
import pytest

from harness.api_helpers import (
    API,
    Org,
    clients,
    create_structure,
    json_body,
    post_record,
    simulated,
    train_fault_mode,
    upload_simulated,
)
from harness.live import DATABASES, LiveServer, on_each_database

T0 = dt.datetime(2026, 3, 1, 6, 0, tzinfo=dt.UTC)
DAY = dt.timedelta(days=1)
# (what is uploaded, acquisition day, the status it must get): uploaded in this order.
PLAN = [
    (("k2", 10.0, 100), 5, "faulty"),
    (("none", 0.0, 100), 1, "healthy"),
    (("noise", 0.0, 200), 8, "unknown_fault"),
    (("k1", 20.0, 100), 3, "faulty"),
    (("k2", 10.0, 101), 3, "faulty"),  # the same time as the one before
    (("none", 0.0, 101), 0, "healthy"),
    (("k1", 20.0, 101), 7, "faulty"),
    (("noise", 0.0, 201), 2, "unknown_fault"),
    (("none", 0.0, 103), 6, "healthy"),
    (("k2", 10.0, 103), 4, "faulty"),
]
PLUS_TWO = dt.timezone(dt.timedelta(hours=2))


def when(day: int) -> dt.datetime:
    return T0 + day * DAY


def parse(text: str) -> dt.datetime:
    return dt.datetime.fromisoformat(text.replace("Z", "+00:00"))


@dataclass
class History:
    org: Org
    structure_id: int
    verdicts: list[dict]  # as returned by the uploads, in upload order

    def url(self, tail: str = "verdicts") -> str:
        return f"{API}/structures/{self.structure_id}/{tail}"


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    return sqlite_api_server


def build_history(api_server: LiveServer) -> History:
    org = Org.create(api_server)
    verdicts = []
    with clients(org) as (admin, ingest, _):
        sid = create_structure(admin, "history")["id"]
        train_fault_mode(admin, ingest, sid, "k2", seed=21)
        train_fault_mode(admin, ingest, sid, "k1", seed=22)
        for index, ((fault, k, seed), day, status) in enumerate(PLAN):
            # One time is written in +02:00: the service must order by the instant, not the text.
            moment = when(day).astimezone(PLUS_TWO) if index == 3 else when(day)
            if fault == "noise":  # two unrelated white signals: no model explains them
                body = json_body(2000, seed=seed, acquired_at=moment.isoformat())
                response = post_record(ingest, sid, body, inspect="true")
                assert response.status_code == 201, response.text
                record = response.json()
            else:
                record = upload_simulated(
                    ingest, sid, simulated(fault, k, seed), inspect="true", acquired_at=moment.isoformat()
                )
            assert record["verdict"]["status"] == status, (fault, k, seed, record["verdict"])
            assert parse(record["acquired_at"]) == when(day)
            verdicts.append(record["verdict"])
    return History(org, sid, verdicts)


@pytest.fixture(scope="module")
def history(api_server: LiveServer) -> History:
    return build_history(api_server)


@pytest.fixture(scope="module", params=DATABASES)
def database_history(request: pytest.FixtureRequest) -> History:
    """The history on each database, for the times it stores and the order it reads them in."""
    return on_each_database(request, "history", build_history)


def listing(client, history: History, **params) -> list[dict]:
    """The whole filtered history in one page."""
    response = client.get(history.url(), params={"limit": 1000, **params})
    assert response.status_code == 200, response.text
    assert response.json()["next_cursor"] is None
    return response.json()["items"]


def ids(verdicts: list[dict]) -> list[int]:
    return [v["id"] for v in verdicts]


@pytest.fixture
def viewer(history: History):
    with history.org.client("viewer") as client:
        yield client


@pytest.fixture
def database_viewer(database_history: History):
    with database_history.org.client("viewer") as client:
        yield client


def test_history_is_newest_first(database_history: History, database_viewer):
    history, viewer = database_history, database_viewer
    items = listing(viewer, history)
    assert len(items) == len(PLAN)
    assert [parse(v["acquired_at"]) for v in items] == sorted((when(day) for _, day, _ in PLAN), reverse=True)
    expected = sorted(history.verdicts, key=lambda v: (parse(v["acquired_at"]), v["id"]), reverse=True)
    # The stored verdicts, unchanged since their uploads (the times compared as instants: see
    # test_an_upload_answers_in_utc_like_everything_else for how they are written).
    assert [{**v, "acquired_at": parse(v["acquired_at"])} for v in items] == [
        {**v, "acquired_at": parse(v["acquired_at"])} for v in expected
    ]
    same_time = [v["id"] for v in items if parse(v["acquired_at"]) == when(3)]
    assert len(same_time) == 2 and same_time[0] > same_time[1]  # ties: the newer id first


def test_an_upload_answers_in_utc_like_everything_else(database_history: History, database_viewer):
    history, viewer = database_history, database_viewer
    """Times are stored and listed in UTC; the answer to the upload that gave one in +02:00 must
    not differ from what GET returns for the same record and verdict."""
    uploaded = history.verdicts[3]
    assert parse(uploaded["acquired_at"]) == when(3)
    fetched = viewer.get(f"{API}/verdicts/{uploaded['id']}").json()
    assert fetched["acquired_at"] == "2026-03-04T06:00:00Z"
    assert uploaded == fetched


def test_history_time_filters(database_history: History, database_viewer):
    history, viewer = database_history, database_viewer
    items = listing(viewer, history)

    def acquired(predicate) -> list[int]:
        return [v["id"] for v in items if predicate(parse(v["acquired_at"]))]

    cases = [
        ({"start": when(3)}, lambda t: t >= when(3)),  # start is inclusive: both day-3 verdicts
        ({"end": when(3)}, lambda t: t < when(3)),  # end is exclusive
        ({"start": when(2), "end": when(6)}, lambda t: when(2) <= t < when(6)),
        ({"start": when(3).astimezone(PLUS_TWO)}, lambda t: t >= when(3)),  # the same instant in +02:00
        ({"end": (when(3) + dt.timedelta(microseconds=1)).isoformat()}, lambda t: t <= when(3)),
        ({"start": when(9)}, lambda t: False),
    ]
    for params, predicate in cases:
        query = {
            name: value if isinstance(value, str) else value.isoformat() for name, value in params.items()
        }
        assert ids(listing(viewer, history, **query)) == acquired(predicate), query
    assert len(acquired(lambda t: t >= when(3))) == 7


def test_history_status_and_fault_mode_filters(history: History, viewer):
    items = listing(viewer, history)
    for status, count in (("healthy", 3), ("faulty", 5), ("unknown_fault", 2)):
        filtered = listing(viewer, history, status=status)
        assert ids(filtered) == [v["id"] for v in items if v["status"] == status]
        assert len(filtered) == count
    for mode, count in (("k1", 2), ("k2", 3), ("k3", 0)):
        filtered = listing(viewer, history, fault_mode=mode)
        assert ids(filtered) == [v["id"] for v in items if v["fault_mode"] == mode]
        assert len(filtered) == count
    combined = listing(viewer, history, status="faulty", fault_mode="k2", start=when(4).isoformat())
    assert ids(combined) == [
        v["id"] for v in items if v["fault_mode"] == "k2" and parse(v["acquired_at"]) >= when(4)
    ]
    assert len(combined) == 2


@pytest.mark.parametrize("limit", [1, 2, 3, 4, 9, 10, 11])
def test_history_cursor_pagination(database_history: History, database_viewer, limit):
    history, viewer = database_history, database_viewer
    everything = listing(viewer, history)
    walked, pages, cursor = [], 0, None
    while True:
        params = {"limit": limit, **({"cursor": cursor} if cursor else {})}
        response = viewer.get(history.url(), params=params)
        assert response.status_code == 200, response.text
        page = response.json()
        pages += 1
        cursor = page["next_cursor"]
        if cursor is not None:
            assert len(page["items"]) == limit
        else:
            assert 0 < len(page["items"]) <= limit
        walked += page["items"]
        if cursor is None:
            break
        assert pages <= len(everything), "the cursor does not advance"
    assert pages == -(-len(everything) // limit)
    assert len(set(ids(walked))) == len(walked)  # no duplicates
    assert walked == everything  # no gaps, same order


def test_history_pagination_with_a_filter(database_history: History, database_viewer):
    history, viewer = database_history, database_viewer
    everything = listing(viewer, history, status="faulty")
    walked, cursor = [], None
    while True:
        params = {"limit": 2, "status": "faulty", **({"cursor": cursor} if cursor else {})}
        page = viewer.get(history.url(), params=params).json()
        walked += page["items"]
        cursor = page["next_cursor"]
        if cursor is None:
            break
    assert walked == everything and len(walked) == 5


def _cursor(text: str) -> str:
    return base64.urlsafe_b64encode(text.encode()).decode()


@pytest.mark.parametrize(
    "cursor",
    [
        "not a cursor",
        "%%%",
        _cursor("nope"),
        _cursor("2026-03-01T00:00:00|5"),  # a naive time
        _cursor("2026-03-01T00:00:00+00:00|five"),
        _cursor("2026-03-01T00:00:00+00:00|5|6"),
        base64.urlsafe_b64encode(b"\xff\xfe|5").decode(),
    ],
)
def test_history_refuses_a_cursor_it_did_not_issue(history: History, viewer, cursor):
    response = viewer.get(history.url(), params={"cursor": cursor})
    assert response.status_code == 422, response.text
    assert (
        response.json()["detail"] == "the cursor is not one this service issued; use next_cursor from a page"
    )


def test_history_refuses_bad_filters(history: History, viewer):
    for name in ("start", "end"):
        response = viewer.get(history.url(), params={name: "2026-03-01T10:00:00"})
        assert response.status_code == 422, response.text
        assert response.json()["detail"] == f"{name} needs a timezone, e.g. 2026-11-21T10:00:00Z"
    for params, location, fragment in (
        ({"status": "broken"}, "status", "'healthy', 'faulty', 'unknown_fault' or 'anomaly'"),
        ({"limit": 0}, "limit", "greater than or equal to 1"),
        ({"limit": 1001}, "limit", "less than or equal to 1000"),
        ({"start": "last tuesday"}, "start", "datetime"),
    ):
        response = viewer.get(history.url(), params=params)
        assert response.status_code == 422, response.text
        (error,) = response.json()["detail"]
        assert error["loc"] == ["query", location] and fragment in error["msg"], error


# --- the summary -----------------------------------------------------------------------------


def test_summary_agrees_with_the_history(history: History, viewer):
    items = listing(viewer, history)
    summary = viewer.get(history.url("summary")).json()
    assert summary["structure_id"] == history.structure_id
    assert summary["total"] == len(items) == 10
    assert summary["counts"] == {
        status: sum(v["status"] == status for v in items)
        for status in ("healthy", "faulty", "unknown_fault", "anomaly")
    }
    assert summary["counts"] == {"healthy": 3, "faulty": 5, "unknown_fault": 2, "anomaly": 0}
    assert summary["latest"] == items[0]
    trend = summary["trend"]
    assert [p["verdict_id"] for p in trend] == ids(items)[::-1]  # oldest to newest
    times = [parse(p["acquired_at"]) for p in trend]
    assert times == sorted(times)
    by_id = {v["id"]: v for v in items}
    for point in trend:
        verdict = by_id[point["verdict_id"]]
        assert {name: point[name] for name in ("status", "fault_mode", "k_hat", "sigma_k")} == {
            name: verdict[name] for name in ("status", "fault_mode", "k_hat", "sigma_k")
        }
    # The latest verdict is an unknown fault: no mode, so no trend of k̂ to fit.
    assert items[0]["status"] == "unknown_fault" and summary["k_hat_slope_per_day"] is None


# A k2 fault growing 5 % a day, uploaded out of order, and a k1 fault among them that the k2
# slope must leave out: (mode, day, k, simulation seed).
GROWTH = [
    ("k2", 2, 15.0, 303),
    ("k2", 0, 5.0, 301),
    ("k1", 0.5, 25.0, 101),
    ("k2", 3, 20.0, 301),
    ("k2", 1, 10.0, 302),
]


def test_summary_slope_of_a_growing_fault(api_server: LiveServer):
    org = Org.create(api_server)
    with clients(org) as (admin, ingest, viewer):
        sid = create_structure(admin, "growth")["id"]
        train_fault_mode(admin, ingest, sid, "k2", seed=31)
        train_fault_mode(admin, ingest, sid, "k1", seed=32)
        url = f"{API}/structures/{sid}/summary"
        empty = viewer.get(url).json()
        assert empty == {
            "structure_id": sid,
            "total": 0,
            "counts": {"healthy": 0, "faulty": 0, "unknown_fault": 0, "anomaly": 0},
            "latest": None,
            "trend": [],
            "k_hat_slope_per_day": None,
        }
        for index, (mode, day, k, seed) in enumerate(GROWTH):
            record = upload_simulated(
                ingest, sid, simulated(mode, k, seed), inspect="true", acquired_at=when(day).isoformat()
            )
            assert (record["verdict"]["status"], record["verdict"]["fault_mode"]) == ("faulty", mode)
            if index == 0:
                assert viewer.get(url).json()["k_hat_slope_per_day"] is None  # one point has no slope
        summary = viewer.get(url).json()
    trend = summary["trend"]
    assert [p["fault_mode"] for p in trend] == ["k2", "k1", "k2", "k2", "k2"]  # oldest first
    assert summary["latest"]["acquired_at"] == trend[-1]["acquired_at"] and parse(
        trend[-1]["acquired_at"]
    ) == when(3)
    days = np.array([(parse(p["acquired_at"]) - T0) / DAY for p in trend])
    k_hat = np.array([p["k_hat"] for p in trend])
    k2 = np.array([p["fault_mode"] == "k2" for p in trend])
    assert list(days[k2]) == [0.0, 1.0, 2.0, 3.0]
    assert np.all(np.abs(k_hat[k2] - [5.0, 10.0, 15.0, 20.0]) < 1.0)
    slope = summary["k_hat_slope_per_day"]
    # The slope of the latest verdict's mode only: the k1 estimate would bend a fit over all points.
    assert slope == pytest.approx(np.polyfit(days[k2], k_hat[k2], 1)[0], rel=1e-6)
    assert slope != pytest.approx(np.polyfit(days, k_hat, 1)[0], abs=0.5)
    assert slope > 0 and slope == pytest.approx(5.0, abs=0.5)


# --- model versions ------------------------------------------------------------------------


def test_model_versions_and_the_verdicts_they_give(api_server: LiveServer):
    org = Org.create(api_server)
    with clients(org) as (admin, ingest, viewer):
        sid = create_structure(admin, "versions")["id"]
        models = f"{API}/structures/{sid}/models"
        first = train_fault_mode(admin, ingest, sid, "k2", seed=41)
        second = train_fault_mode(admin, ingest, sid, "k2", seed=42)
        k1 = train_fault_mode(admin, ingest, sid, "k1", seed=43)
        assert (first["version"], first["active"], second["version"], second["active"]) == (1, True, 2, True)

        def listed() -> set[tuple[str, int, bool]]:
            return {(m["name"], m["version"], m["active"]) for m in viewer.get(models).json()}

        assert listed() == {("k2", 1, False), ("k2", 2, True), ("k1", 1, True)}

        def used(*versions: dict) -> list[dict]:
            return [{"id": v["id"], "name": v["name"], "version": v["version"]} for v in versions]

        record = upload_simulated(ingest, sid, simulated("k2", 10.0, 105), inspect="true")
        under_second = record["verdict"]
        assert under_second["model_versions"] == used(k1, second)

        activated = admin.post(f"{models}/{first['id']}/activate")
        assert activated.status_code == 200, activated.text
        assert (activated.json()["id"], activated.json()["active"]) == (first["id"], True)
        assert listed() == {("k2", 1, True), ("k2", 2, False), ("k1", 1, True)}  # k1 untouched

        inspect = f"{API}/records/{record['id']}/inspect"
        under_first = ingest.post(inspect).json()
        assert under_first["id"] != under_second["id"] and under_first["record_id"] == record["id"]
        assert under_first["model_versions"] == used(k1, first)
        assert ingest.post(inspect).json()["id"] == under_first["id"]  # same model set, same verdict
        again = upload_simulated(ingest, sid, simulated("k2", 10.0, 105), inspect="true")
        assert (again["created"], again["id"], again["verdict"]["id"]) == (
            False,
            record["id"],
            under_first["id"],
        )

        assert admin.post(f"{models}/{second['id']}/activate").status_code == 200
        assert ingest.post(inspect).json() == under_second  # back to the first verdict, unchanged
        assert viewer.get(f"{API}/verdicts/{under_first['id']}").json() == under_first
        history = viewer.get(f"{API}/structures/{sid}/verdicts").json()["items"]
        assert sorted(v["id"] for v in history if v["record_id"] == record["id"]) == sorted(
            [under_first["id"], under_second["id"]]
        )
        assert admin.post(f"{models}/{second['id']}/activate").status_code == 200  # idempotent
        assert listed() == {("k2", 1, False), ("k2", 2, True), ("k1", 1, True)}


def test_health_and_readiness(database_server: LiveServer):
    """Readiness is the database answering."""
    with database_server.client() as anonymous:  # no key needed
        healthz, readyz = anonymous.get("/healthz"), anonymous.get("/readyz")
    assert (healthz.status_code, healthz.json()) == (200, {"status": "ok"})
    assert (readyz.status_code, readyz.json()) == (200, {"status": "ready"})
