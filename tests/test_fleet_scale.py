"""Counts and standings kept on write, and the fleet listed a page at a time, on both databases.

``/metrics``, the summary and the fleet views read each structure's state row
(``structure_states``) and the ended-job counts (``job_counts``) instead of the history. Here
they are held, after every step of a sequence of uploads, inspections and jobs (records uploaded
late, two at one instant, the same data twice, concurrent uploads), against what the tables
themselves hold, counted with ``COUNT(*)`` and walked in Python. Each database gets a server of
its own (the embedded job backend, on PostgreSQL too), so that nothing else writes meanwhile.

What the database decides (counts kept by its writes, concurrent writers, the times it stores,
the name filter's LIKE) on both; refusals and links on SQLite (``sqlite_fleet_server``).
"""

from __future__ import annotations

import datetime as dt
import html as markup
import re
import threading
import uuid
from dataclasses import dataclass

import httpx
import pytest
from sqlalchemy import Engine, insert, select, text, update

from harness.api_helpers import (
    API,
    Org,
    clients,
    create_structure,
    csv_text,
    detail,
    json_body,
    noise,
    nothing_written,
    npz_bytes,
    post_record,
    record_set_csv,
    simulated,
    train_fault_mode,
    upload_simulated,
    verdicts,
    wait_for,
)
from harness.dashboard_helpers import DASHBOARD, logged_in
from harness.fleet import FUTURE, SKEW, STATUSES, Fleet, counted, kept, scraped, walked
from service.jobs import embedded
from service.tables import Alarm, Job, JobCount, Record, Structure, StructureState, Verdict

T0 = dt.datetime(2026, 6, 1, 6, 0, tzinfo=dt.UTC)


def assert_exact(fleet: Fleet, *structure_ids: int) -> None:
    assert scraped(fleet.server) == counted(fleet.engine)
    for structure_id in structure_ids:
        assert kept(fleet.engine, structure_id) == walked(fleet.engine, structure_id), structure_id


# --- uploads --------------------------------------------------------------------------------


def upload(
    ingest: httpx.Client, structure_id: int, status: str, day: float, seed: int, **params: str
) -> dict:
    """A record that the structure's k2 model judges ``status``, acquired on ``day`` after T0."""
    acquired_at = T0 + dt.timedelta(days=day)
    params = {"inspect": "true", **params}
    if status == "unknown_fault":  # two unrelated white signals: no model explains them
        body = json_body(2000, seed=seed, acquired_at=acquired_at.isoformat())
        response = post_record(ingest, structure_id, body, **params)
    else:
        fault, k = ("none", 0.0) if status == "healthy" else ("k2", 20.0)
        record = simulated(fault, k, [seed, 7])
        body = npz_bytes(x=record.x, y=record.y, fs=record.fs)
        response = post_record(
            ingest, structure_id, body, "application/x-npz", acquired_at=acquired_at.isoformat(), **params
        )
    expected = 202 if params["inspect"] == "queue" else 201
    assert response.status_code in (200, expected), response.text
    assert dt.datetime.fromisoformat(response.json()["acquired_at"]) == acquired_at
    return response.json()


# (status, acquisition day): uploaded in this order, many of them late, so that the current run
# grows backwards, is cut short and grows again; two pairs share an instant.
PLAN = [
    ("faulty", 5),
    ("healthy", 1),
    ("faulty", 3),  # late, and of the latest's status: the run now starts on day 3
    ("healthy", 4),  # late, of another status: the run starts on day 5 again
    ("faulty", 5),  # the same instant as the first: newer by its id
    ("unknown_fault", 8),
    ("unknown_fault", 2),
    ("unknown_fault", 8),
    ("healthy", 0),
]


def test_counts_and_standings_stay_exact_through_uploads_inspections_and_jobs(fleet_server: Fleet):
    org = Org.create(fleet_server.server)
    with clients(org) as (admin, ingest, viewer):
        sid = create_structure(admin, "plan")["id"]
        other = create_structure(admin, "untouched")["id"]
        assert_exact(fleet_server, sid, other)  # two structures, nothing stored yet
        train_fault_mode(admin, ingest, sid, "k2", seed=31)
        assert_exact(fleet_server, sid, other)  # the training's records, no verdict
        verdicts = []
        for index, (status, day) in enumerate(PLAN):
            answer = upload(ingest, sid, status, day, seed=300 + index)
            assert answer["verdict"]["status"] == status
            verdicts.append(answer["verdict"])
            assert_exact(fleet_server, sid, other)
        # The same data again is the same record: no count moves.
        again = upload(ingest, sid, *PLAN[-1], seed=300 + len(PLAN) - 1)
        assert again["id"] == verdicts[-1]["record_id"]
        assert_exact(fleet_server, sid, other)

        # Stored now, inspected later through the API; and one inspected by a queued job.
        stored = upload(ingest, sid, "faulty", 2.5, seed=400, inspect="false")
        assert_exact(fleet_server, sid, other)
        response = ingest.post(f"{API}/records/{stored['id']}/inspect")
        assert response.status_code in (200, 201), response.text
        assert_exact(fleet_server, sid, other)
        queued = upload(ingest, sid, "healthy", 9, seed=401, inspect="queue")

        def inspected() -> bool:
            latest = viewer.get(f"{API}/structures/{sid}/summary").json()["latest"]
            return latest is not None and latest["record_id"] == queued["id"]

        wait_for(inspected, 60, "the queued inspection")
        wait_for(lambda: counted(fleet_server.engine)["jobs"]["done"] >= 1, 30, "the job's end")
        assert_exact(fleet_server, sid, other)
        assert kept(fleet_server.engine, sid)["status"] == "healthy"

        summary = viewer.get(f"{API}/structures/{sid}/summary").json()
        walk = walked(fleet_server.engine, sid)
        item = next(s for s in viewer.get(f"{API}/structures").json() if s["id"] == sid)
        assert (item["status"], dt.datetime.fromisoformat(item["since"])) == (walk["status"], walk["since"])
        assert summary["counts"] == {status: walk[status] for status in STATUSES}
        assert summary["total"] == sum(walk[status] for status in STATUSES) == len(PLAN) + 2


def test_concurrent_uploads_lose_no_count(fleet_server: Fleet):
    """Twelve uploads at once, each inspected, to one structure (and four to another): every
    increment lands, whichever transaction waited for which."""
    org = Org.create(fleet_server.server)
    with clients(org) as (admin, ingest, _):
        busy = create_structure(admin, "busy")["id"]
        quiet = create_structure(admin, "quiet")["id"]
        for sid, seed in ((busy, 41), (quiet, 42)):
            train_fault_mode(admin, ingest, sid, "k2", seed=seed)
    before = counted(fleet_server.engine)
    plan = [(busy, index) for index in range(12)] + [(quiet, index) for index in range(4)]
    start = threading.Barrier(len(plan))
    failures: list[str] = []

    def one(sid: int, index: int) -> None:
        with org.client("ingest") as client:
            start.wait()
            try:
                status = ("healthy", "faulty", "unknown_fault")[index % 3]
                upload(client, sid, status, day=index / 10, seed=500 + index)
            except AssertionError as exc:
                failures.append(str(exc))

    threads = [threading.Thread(target=one, args=args) for args in plan]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert failures == []
    after = counted(fleet_server.engine)
    assert after["records"] - before["records"] == len(plan)
    assert sum(after["verdicts"].values()) - sum(before["verdicts"].values()) == len(plan)
    assert_exact(fleet_server, busy, quiet)


def test_a_job_whose_claim_was_taken_over_is_counted_once(fleet_server: Fleet):
    """A worker whose lease ran out and whose job another worker claimed since does not end the
    job: the new claim does, once, and the count of jobs done grows by one. The job is due only
    tomorrow, so the server's own worker leaves it to the claims made here, at tomorrow's times."""
    sessions = fleet_server.server.app.state.sessions
    tomorrow = dt.datetime.now(dt.UTC) + dt.timedelta(days=1)
    with sessions() as session:
        organisation_id = session.execute(text("SELECT min(id) FROM organisations")).scalar_one()
        values = {
            "organisation_id": organisation_id,
            "task": "inspect_record",
            "args": {"record_id": 2**31 - 1},  # no such record: the task has nothing to do
            "run_after": tomorrow,
        }
        job_id = session.execute(insert(Job).values(values).returning(Job.id)).scalar_one()
        session.commit()
        done_before = session.scalar(select(JobCount.count).where(JobCount.state == "done"))
    with sessions() as session:
        first = embedded.claim(session, now=tomorrow)
        second = embedded.claim(session, now=tomorrow + 2 * embedded.LEASE)  # the first lease ran out
    assert first is not None and second is not None and first.id == second.id == job_id
    assert second.attempts == first.attempts + 1
    settings = fleet_server.server.settings
    with sessions() as session:
        embedded.run(session, first, settings)
        assert session.get(Job, job_id).status == "running"  # still the second claim's
        embedded.run(session, second, settings)
    with sessions() as session:
        assert session.get(Job, job_id).status == "done"
        done = session.scalar(select(JobCount.count).where(JobCount.state == "done"))
    assert done == done_before + 1
    assert scraped(fleet_server.server) == counted(fleet_server.engine)


# --- acquisition times past the server's clock ------------------------------------------------


@pytest.fixture(scope="module")
def clocked(sqlite_fleet_server: Fleet) -> tuple[Org, int]:
    """An organisation and its structure with a k2 model, which inspects what it is sent."""
    org = Org.create(sqlite_fleet_server.server)
    with clients(org) as (admin, ingest, _):
        sid = create_structure(admin, "clocked")["id"]
        train_fault_mode(admin, ingest, sid, "k2", seed=71)
    return org, sid


def _send(ingest: httpx.Client, sid: int, route: str, when: str, seed: int) -> httpx.Response:
    """A record (a set of two on the route "set") acquired at ``when``, on one of the ways in."""
    if route == "set":
        body = record_set_csv(2, 500, seed)
        return ingest.post(f"{API}/structures/{sid}/record-sets", content=body, params={"acquired_at": when},
                           headers={"Content-Type": "text/csv"})  # fmt: skip
    if route == "csv":
        return post_record(ingest, sid, csv_text(*noise(2000, seed)), "text/csv", acquired_at=when)
    inspect = "queue" if route == "json, queued" else "true"
    return post_record(ingest, sid, json_body(2000, seed=seed, acquired_at=when), inspect=inspect)


@pytest.mark.parametrize("route", ["json", "json, queued", "csv", "set"])
def test_an_acquisition_time_past_the_servers_clock_is_refused_before_anything_is_written(
    clocked: tuple[Org, int], route: str
):
    """9999-12-31, or a minute more than the skew allowed ahead of the server's clock: 422 naming
    the server's clock (ISO 8601, UTC) and the setting, nothing stored or queued. Half the skew
    ahead is a clock a little fast: stored at the time given and, inspected now or by a job,
    the structure's latest verdict."""
    org, sid = clocked
    seed = 90 + ["json", "json, queued", "csv", "set"].index(route)
    beyond = (dt.datetime.now(dt.UTC) + SKEW + dt.timedelta(minutes=1)).isoformat()
    with clients(org) as (_, ingest, viewer):
        for when in ("9999-12-31T00:00:00Z", beyond):
            with nothing_written(org, sid):
                response = _send(ingest, sid, route, when, seed)
            assert response.status_code == 422, response.text
            message = detail(response)
            assert "NARXWATCH_MAX_CLOCK_SKEW_SECONDS (300 s)" in message and "in the future" in message
            clock = re.search(r"later than the server's clock \((\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ)\)", message)
            assert clock is not None, message
            off = dt.datetime.fromisoformat(clock[1]) - dt.datetime.now(dt.UTC)
            assert abs(off) < dt.timedelta(minutes=1)
        fast = dt.datetime.now(dt.UTC).replace(microsecond=0) + SKEW / 2
        response = _send(ingest, sid, route, fast.isoformat(), seed)
        assert response.status_code in (201, 202), response.text
        answers = response.json() if route == "set" else [response.json()]
        assert [dt.datetime.fromisoformat(a["acquired_at"]) for a in answers] == [fast] * len(answers)
        if route.startswith("json"):

            def latest() -> dict | None:
                found = viewer.get(f"{API}/structures/{sid}/summary").json()["latest"]
                return found if found and found["record_id"] == answers[0]["id"] else None

            judged = wait_for(latest, 60, "the verdict of the record a little ahead")
            assert dt.datetime.fromisoformat(judged["acquired_at"]) == fast  # type: ignore[index]


def test_a_record_from_the_future_already_stored_hides_no_fault(fleet_server: Fleet):
    """A structure healthy yesterday whose database holds a healthy record dated 9999-12-31, as
    an upload stored it before acquisition times were checked (its state too: the latest, healthy
    since 9999). A 30 % k2 fault acquired now makes it faulty since now in the fleet list, the
    summary and the dashboard; a healthy record uploaded late then leaves that run as it is."""
    org = Org.create(fleet_server.server)
    with clients(org) as (admin, ingest, viewer):
        sid = create_structure(admin, "a clock once wrong")["id"]
        train_fault_mode(admin, ingest, sid, "k2", seed=72)
        yesterday = (dt.datetime.now(dt.UTC) - dt.timedelta(days=1)).isoformat()
        upload_simulated(ingest, sid, simulated("none", 0.0, 73), inspect="true", acquired_at=yesterday)
        future = _stored_from_the_future(fleet_server.engine, sid, "healthy")
        fault = upload_simulated(ingest, sid, simulated("k2", 30.0, 74), inspect="true")
        assert fault["verdict"]["status"] == "faulty"
        now = dt.datetime.fromisoformat(fault["acquired_at"])

        def standing() -> tuple[str, dt.datetime]:
            item = next(s for s in viewer.get(f"{API}/structures").json() if s["id"] == sid)
            return item["status"], dt.datetime.fromisoformat(item["since"])

        assert standing() == ("faulty", now)
        summary = viewer.get(f"{API}/structures/{sid}/summary").json()
        assert summary["latest"]["id"] == fault["verdict"]["id"]
        assert summary["trend"][-1]["verdict_id"] == fault["verdict"]["id"]
        # the future one counted
        assert summary["counts"] == {"healthy": 2, "faulty": 1, "unknown_fault": 0, "anomaly": 0}
        assert future in {v["id"] for v in verdicts(viewer, sid)}  # and listed in the history
        assert_exact(fleet_server, sid)
        with logged_in(fleet_server.server, org.keys["viewer"]) as client:
            page = client.get(f"{DASHBOARD}/structures/{sid}").text
            card = re.search(r'<section class="card status-(\w+)" id="standing">.*?</section>', page, re.S)
            row = re.search(
                rf'<tr class="status-(\w+)" data-structure-id="{sid}">.*?</tr>',
                client.get(DASHBOARD).text,
                re.S,
            )
        since = now.strftime("%Y-%m-%d %H:%M:%S UTC")
        for shown in (card, row):
            assert (
                shown is not None
                and shown[1] == "faulty"
                and since in shown[0]
                and "9999-12-31" not in shown[0]
            )

        late = (now - dt.timedelta(hours=12)).isoformat()
        upload_simulated(ingest, sid, simulated("none", 0.0, 75), inspect="true", acquired_at=late)
        assert standing() == ("faulty", now)
        assert_exact(fleet_server, sid)


def _stored_from_the_future(engine: Engine, structure_id: int, status: str) -> int:
    """A record acquired on 9999-12-31 and its verdict written into the tables, and the structure's
    state as the code before acquisition times were checked left it: that verdict its latest,
    ``status`` since 9999. Its verdict's id."""
    with engine.begin() as connection:
        record = dict(structure_id=structure_id, fs=1500.0, n_samples=3, acquired_at=FUTURE,
                      sha256=uuid.uuid4().hex * 2, x=b"", y=b"")  # fmt: skip
        record_id = connection.execute(insert(Record).returning(Record.id), record).scalar_one()
        verdict = dict(record_id=record_id, structure_id=structure_id, acquired_at=FUTURE, model_set="future",
                       status=status, fault_detected=status != "healthy", alpha=0.05, lags=40, n_samples=3,
                       z_critical=1.96, q_critical_detection=40.0, detected_by=[], modes=[])  # fmt: skip
        verdict_id = connection.execute(insert(Verdict).returning(Verdict.id), verdict).scalar_one()
        connection.execute(
            update(StructureState)
            .where(StructureState.structure_id == structure_id)
            .values(status=status, since=FUTURE, latest_verdict_id=verdict_id, latest_acquired_at=FUTURE)
            .values({status: getattr(StructureState, status) + 1, "records": StructureState.records + 1})
        )
    return verdict_id


# --- the fleet a page at a time -------------------------------------------------------------


@dataclass
class Listed:
    org: Org
    ids: dict[str, int]  # name -> id
    standing: dict[str, str]  # name -> status, or "uninspected"


NAMES = ["North bridge", "south-BRIDGE", "tower_1", "tower%2", "mast", "pylon 7", "pylon 8"]


@pytest.fixture(scope="module")
def listed(fleet_server: Fleet) -> tuple[Listed, Listed]:
    """Two organisations: the first with seven structures (three inspected, one of each status),
    the second with two, one named as one of the first's."""
    org = Org.create(fleet_server.server)
    with clients(org) as (admin, ingest, _):
        ids = {name: create_structure(admin, name)["id"] for name in NAMES}
        standing = dict.fromkeys(NAMES, "uninspected")
        for name, status, seed in (
            ("North bridge", "faulty", 61),
            ("mast", "healthy", 62),
            ("pylon 8", "unknown_fault", 63),
        ):
            train_fault_mode(admin, ingest, ids[name], "k2", seed=seed)
            upload(ingest, ids[name], status, day=1, seed=seed)
            standing[name] = status
    theirs = Org.create(fleet_server.server)
    with clients(theirs) as (admin, _, _):
        their_ids = {name: create_structure(admin, name)["id"] for name in ("mast", "their bridge")}
    return Listed(org, ids, standing), Listed(theirs, their_ids, dict.fromkeys(their_ids, "uninspected"))


def every_page(client: httpx.Client, **params: object) -> list[list[dict]]:
    """The pages of ``GET /structures``, following each ``next`` link to the last."""
    pages = []
    response = client.get(f"{API}/structures", params=params)
    while True:
        assert response.status_code == 200, response.text
        pages.append(response.json())
        if "next" not in response.links:
            return pages
        response = client.get(response.links["next"]["url"])


def test_structures_are_listed_a_page_at_a_time_in_order_of_id(listed):
    ours, theirs = listed
    with ours.org.client("viewer") as viewer:
        whole = viewer.get(f"{API}/structures")
        assert whole.status_code == 200 and "link" not in whole.headers  # fewer than a default page
        assert [s["id"] for s in whole.json()] == sorted(ours.ids.values())
        pages = every_page(viewer, limit=3)
    assert [len(page) for page in pages] == [3, 3, 1]
    assert [s["id"] for page in pages for s in page] == sorted(ours.ids.values())
    with theirs.org.client("viewer") as viewer:
        assert [s["id"] for page in every_page(viewer, limit=1) for s in page] == sorted(theirs.ids.values())


@pytest.mark.parametrize(
    ("params", "expected"),
    [
        ({"status": "faulty"}, ["North bridge"]),
        ({"status": "healthy"}, ["mast"]),
        ({"status": "unknown_fault"}, ["pylon 8"]),
        ({"status": "uninspected"}, ["south-BRIDGE", "tower_1", "tower%2", "pylon 7"]),
        ({"name": "bridge"}, ["North bridge", "south-BRIDGE"]),  # any case
        ({"name": "_"}, ["tower_1"]),  # LIKE's wildcards are plain characters
        ({"name": "%"}, ["tower%2"]),
        ({"name": "pylon", "status": "uninspected"}, ["pylon 7"]),
        ({"name": "nothing like it"}, []),
    ],
)
def test_structures_are_filtered_by_status_and_name_on_every_page(listed, params, expected):
    ours, _ = listed
    with ours.org.client("viewer") as viewer:
        pages = every_page(viewer, limit=1, **params)  # the filters ride along in each next link
    items = [s for page in pages for s in page]
    assert [s["name"] for s in items] == sorted(expected, key=ours.ids.__getitem__)
    for item in items:  # each listed with where it stands
        assert (item["status"] or "uninspected") == ours.standing[item["name"]]
        assert (item["since"] is None) == (item["status"] is None)


def test_paging_never_shows_another_organisations_structures(listed):
    ours, theirs = listed
    with ours.org.client("viewer") as viewer:
        first = viewer.get(f"{API}/structures", params={"limit": 1})
        our_cursor = httpx.URL(first.links["next"]["url"]).params["cursor"]
        assert viewer.get(f"{API}/structures", params={"name": "their"}).json() == []
    with theirs.org.client("viewer") as viewer:
        # Our cursor is a position in order of id, not a key to our structures.
        listed_after = viewer.get(f"{API}/structures", params={"cursor": our_cursor}).json()
        assert {s["id"] for s in listed_after} <= set(theirs.ids.values())
        assert [s["id"] for s in viewer.get(f"{API}/structures", params={"name": "mast"}).json()] == [
            theirs.ids["mast"]
        ]
        assert viewer.get(f"{API}/structures", params={"status": "healthy"}).json() == []


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"cursor": "not-a-cursor"}, "cursor"),
        ({"cursor": "c3RydWN0dXJlfDA="}, "cursor"),  # base64 of "structure|0": no id is 0
        ({"cursor": "dmVyZGljdHwx"}, "cursor"),  # base64 of "verdict|1": another listing's
        ({"limit": 0}, "limit"),
        ({"limit": 1001}, "limit"),
        ({"limit": "many"}, "limit"),
        ({"status": "broken"}, "uninspected"),  # the message lists what is allowed
        ({"name": "x" * 201}, "name"),
        ({"name": "a\x00b"}, "name"),  # no name holds a control character
    ],
)
def test_bad_paging_and_filters_are_refused_with_a_clear_422(listed, params, message):
    ours, _ = listed
    with ours.org.client("viewer") as viewer:
        response = viewer.get(f"{API}/structures", params=params)
    assert response.status_code == 422, response.text
    assert message in detail(response)


def test_the_fleet_page_is_paged_and_filtered_from_the_state_rows(fleet_server: Fleet, listed):
    ours, _ = listed
    with logged_in(fleet_server.server, ours.org.keys["viewer"]) as client:
        page = client.get(DASHBOARD)
        assert page.status_code == 200
        shown = [int(i) for i in _row_ids(page.text)]
        assert shown == sorted(ours.ids.values())
        assert "their bridge" not in page.text
        faulty = client.get(DASHBOARD, params={"status": "faulty"})
        assert _row_ids(faulty.text) == [str(ours.ids["North bridge"])]
        assert 'class="status-faulty"' in faulty.text
        named = client.get(DASHBOARD, params={"name": "TOWER"})
        assert _row_ids(named.text) == [str(ours.ids["tower_1"]), str(ours.ids["tower%2"])]
        nothing = client.get(DASHBOARD, params={"name": "their"})
        assert _row_ids(nothing.text) == [] and 'id="no-match"' in nothing.text
        submitted_empty = client.get(DASHBOARD, params={"status": "", "name": ""})  # the form, untouched
        assert _row_ids(submitted_empty.text) == _row_ids(page.text)
        for params in ({"status": "broken"}, {"cursor": "not-a-cursor"}, {"name": "a\x00b"}):
            refused = client.get(DASHBOARD, params=params)
            assert refused.status_code == 422, params


def test_the_fleet_page_links_to_the_next_page(sqlite_fleet_server: Fleet):
    """One structure more than a page: the first page links to the next, which holds it."""
    from service.dashboard.views import FLEET_PAGE

    org = Org.create(sqlite_fleet_server.server)
    with clients(org) as (admin, _, _):
        ids = [create_structure(admin, f"unit {index}")["id"] for index in range(FLEET_PAGE + 1)]
    with logged_in(sqlite_fleet_server.server, org.keys["viewer"]) as client:
        first = client.get(DASHBOARD)
        assert _row_ids(first.text) == [str(i) for i in ids[:FLEET_PAGE]]
        second = client.get(DASHBOARD + _next_link(first.text))
        assert _row_ids(second.text) == [str(ids[-1])] and _next_link(second.text) is None


def test_the_fleet_page_shows_the_oldest_open_alarms_and_counts_the_rest(sqlite_fleet_server: Fleet):
    """A fleet with more open alarms than the page lists: the oldest, the count of all, no other
    organisation's. (All of them made a fleet of 10 000 structures, a tenth in alarm, 460 KB.)"""
    from service.dashboard.views import FLEET_ALARMS

    org, theirs = Org.create(sqlite_fleet_server.server), Org.create(sqlite_fleet_server.server)
    with clients(org) as (admin, _, _), clients(theirs) as (their_admin, _, _):
        sid, their_sid = create_structure(admin)["id"], create_structure(their_admin)["id"]
    with sqlite_fleet_server.engine.begin() as connection:
        owner = dict(
            connection.execute(
                select(Structure.id, Structure.organisation_id).where(Structure.id.in_((sid, their_sid)))
            ).all()
        )
        rows = [
            {"structure_id": structure_id, "organisation_id": owner[structure_id], "rule_kind": "severity"}
            | {"rule": {"threshold": 10.0}, "fault_mode": f"mode{i}"}
            | {"state": "open", "triggered_at": T0, "evaluated_through": T0}
            for structure_id, count in ((sid, FLEET_ALARMS + 2), (their_sid, 3))
            for i in range(count)
        ]
        ids = list(connection.scalars(insert(Alarm).returning(Alarm.id, sort_by_parameter_order=True), rows))
    with logged_in(sqlite_fleet_server.server, org.keys["viewer"]) as client:
        page = client.get(DASHBOARD)
    assert page.status_code == 200
    assert [int(i) for i in re.findall(r'data-alarm-id="(\d+)"', page.text)] == ids[:FLEET_ALARMS]
    assert f"The {FLEET_ALARMS} oldest of {FLEET_ALARMS + 2} open or acknowledged alarms" in page.text


def _row_ids(html: str) -> list[str]:
    return re.findall(r'<tr class="status-[a-z_]+" data-structure-id="(\d+)"', html)


def _next_link(html: str) -> str | None:
    found = re.search(r'<a href="(\?[^"]*)" id="next">', html)
    return markup.unescape(found.group(1)) if found else None
