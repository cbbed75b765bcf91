"""Alarms through HTTP: rules, the lifecycle, roles, tenancy, bad input.

A rig with a k2 fault-mode model is fed simulated records, healthy then with a k2 fault of 25 %,
each inspected on upload (or by a queued job). What the rules must do is worked out here from the
verdicts the service returned, by the rule's own definition (k of the last m; a CUSUM written out
in this file), and compared with the alarms the service opened and resolved.

The rules are the service's whatever the database: on SQLite. What the database decides (one
unresolved alarm a key, kept by its index; verdicts stored at once, serialised by the structure's
row lock) on PostgreSQL too: the tests that take ``database_server``; the listing's plan on
PostgreSQL alone.
"""

from __future__ import annotations

import datetime as dt
import uuid
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import pytest
from sqlalchemy import event, text
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from harness.api_helpers import (
    API,
    CUSUM_TRAINING_K,
    RIG_TERMS,
    TRAINING_K,
    Org,
    clients,
    create_structure,
    detail,
    experiments,
    npz_bytes,
    post_record,
    simulated,
    train_fault_mode,
    wait_for,
)
from harness.live import LiveServer
from models.alarms import DESIGN_SHIFT, design_cusum, in_control_arl
from service.db import make_engine
from service.domain import alarms
from service.security import Principal, Role
from service.tables import Alarm, Structure, utcnow

T0 = dt.datetime(2026, 5, 1, 6, 0, tzinfo=dt.UTC)
STEP = dt.timedelta(hours=6)
FAULT_K = 25.0
PERSISTENCE = {"kind": "persistence", "k": 2, "m": 3, "clear_after": 2}
STEP_K = 0.2  # % of k2: about three σ̂k a record


@dataclass
class Rig:
    org: Org
    structure_id: int
    uploaded: int = 0  # records uploaded so far: the next one is acquired STEP later

    def upload(self, k: float, seed: int, **params: str) -> dict:
        """A simulated record with a k2 fault of ``k`` %, inspected on upload by default."""
        with self.org.client("ingest") as ingest:
            record = simulated("k2", k, [seed, self.uploaded], 2000)
            moment = T0 + self.uploaded * STEP
            self.uploaded += 1
            params = {"inspect": "true"} | params
            body = npz_bytes(x=record.x, y=record.y, fs=record.fs)
            params |= {"acquired_at": moment.isoformat()}
            response = post_record(ingest, self.structure_id, body, "application/x-npz", **params)
            assert response.status_code in (201, 202), response.text
            return response.json()

    def alarms(self, **filters: object) -> list[dict]:
        with self.org.client("viewer") as viewer:
            response = viewer.get(f"{API}/alarms", params={"structure_id": self.structure_id, **filters})
            assert response.status_code == 200, response.text
            return response.json()["items"]


def new_rig(
    server: LiveServer, seed: int, rules: list[dict] | None, magnitudes: tuple[float, ...] = TRAINING_K
) -> Rig:
    """A structure with a k2 model trained on experiments at ``magnitudes``, watched by ``rules``."""
    org = Org.create(server)
    with clients(org) as (admin, ingest, _):
        structure_id = create_structure(admin, f"alarmed-{uuid.uuid4().hex[:6]}")["id"]
        body = {
            "name": "k2",
            "k_min": -32.0,
            "k_max": 32.0,
            "experiments": experiments(ingest, structure_id, "k2", seed, magnitudes),
            "terms": RIG_TERMS,
        }
        response = admin.post(f"{API}/structures/{structure_id}/models/fault-modes", json=body)
        assert response.status_code == 201, response.text
        if rules is not None:
            response = admin.put(f"{API}/structures/{structure_id}/alarm-rules", json={"rules": rules})
            assert response.status_code == 200, response.text
    return Rig(org, structure_id)


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    return sqlite_api_server


@pytest.fixture(scope="module")
def rig(api_server: LiveServer) -> Rig:
    return new_rig(api_server, seed=61, rules=[PERSISTENCE])


def when(text: str) -> dt.datetime:
    return dt.datetime.fromisoformat(text.replace("Z", "+00:00"))


def statuses(records: list[dict]) -> list[str]:
    return [r["verdict"]["status"] for r in records]


def test_an_alarm_opens_once_is_acknowledged_by_an_admin_and_resolves_when_the_rule_clears(rig: Rig):
    healthy = [rig.upload(0.0, 1) for _ in range(2)]
    assert statuses(healthy) == ["healthy", "healthy"]
    assert rig.alarms() == []
    faulty = [rig.upload(FAULT_K, 2) for _ in range(3)]
    assert statuses(faulty) == ["faulty"] * 3
    # 2 of the last 3 faulty first holds at the second faulty record; the third keeps the same alarm.
    (alarm,) = rig.alarms()
    assert (alarm["rule_kind"], alarm["fault_mode"], alarm["state"]) == ("persistence", None, "open")
    assert alarm["record_id"] == faulty[1]["id"]
    assert when(alarm["triggered_at"]) == when(faulty[1]["acquired_at"])
    assert alarm["rule"] == PERSISTENCE

    with clients(rig.org) as (admin, ingest, viewer):
        url = f"{API}/alarms/{alarm['id']}"
        assert viewer.get(url).json()["state"] == "open"
        refused = ingest.post(f"{url}/acknowledge", json={"note": "on it"})
        assert refused.status_code == 403 and "admin" in detail(refused) and "ingest" in detail(refused)
        assert viewer.post(f"{url}/acknowledge", json={}).status_code == 403
        assert admin.post(f"{url}/acknowledge", json={"note": "x" * 2001}).status_code == 422
        assert viewer.get(url).json()["state"] == "open", "a refused acknowledgement changed nothing"
        acknowledged = admin.post(f"{url}/acknowledge", json={"note": "crew sent to bay 3"})
        assert acknowledged.status_code == 200, acknowledged.text
        body = acknowledged.json()
        assert body["state"] == "acknowledged" and body["acknowledgement_note"] == "crew sent to bay 3"
        assert body["acknowledged_by"] == rig.org.keys["admin"].split("_")[1]
        again = admin.post(f"{url}/acknowledge", json={})
        assert again.status_code == 409 and "acknowledged" in detail(again)

    # Healthy again: the rule still holds on the first healthy record (2 of the last 3), then
    # clears; two records in a row without it resolve the alarm.
    recovered = [rig.upload(0.0, 3) for _ in range(3)]
    assert statuses(recovered) == ["healthy"] * 3
    (resolved,) = rig.alarms()
    assert resolved["state"] == "resolved" and resolved["resolution"] == "cleared"
    assert resolved["resolved_by"] is None
    with clients(rig.org) as (_, _, viewer):
        transitions = viewer.get(f"{API}/alarms/{alarm['id']}").json()["transitions"]
    assert [(t["from_state"], t["to_state"]) for t in transitions] == [
        (None, "open"),
        ("open", "acknowledged"),
        ("acknowledged", "resolved"),
    ]
    assert [t["by"] for t in transitions] == [None, rig.org.keys["admin"].split("_")[1], None]
    assert transitions[1]["note"] == "crew sent to bay 3"


def test_an_alarm_resolved_by_hand_is_not_reopened_by_the_evidence_it_was_resolved_on(rig: Rig):
    before = {a["id"] for a in rig.alarms()}
    first = rig.upload(FAULT_K, 4)
    # A queued inspection stores its verdict in a job: the alarm is raised there.
    rig.upload(FAULT_K, 5, inspect="queue")
    opened = wait_for(
        lambda: [a for a in rig.alarms(state="open") if a["id"] not in before],
        60,
        "the queued verdict's alarm",
    )
    (alarm,) = opened  # type: ignore[misc]
    assert alarm["record_id"] != first["id"], "it fired on the queued record, the second faulty one"
    with clients(rig.org) as (admin, _, _):
        response = admin.post(f"{API}/alarms/{alarm['id']}/resolve", json={"note": "sensor cable replaced"})
        assert response.status_code == 200, response.text
        assert response.json()["resolution"] == "by_hand"
        assert admin.post(f"{API}/alarms/{alarm['id']}/resolve", json={}).status_code == 409
    # The window still holds two faulty records, but they were judged already.
    assert statuses([rig.upload(0.0, 6)]) == ["healthy"]
    assert rig.alarms(state="open") == [] and rig.alarms(state="acknowledged") == []


def test_the_cusum_fires_on_its_designed_threshold_and_reports_when_the_drift_began(api_server: LiveServer):
    rule = {"kind": "cusum", "false_alarms_per_year": 1.0, "records_per_day": 4.0}
    rig = new_rig(api_server, seed=62, rules=[rule], magnitudes=CUSUM_TRAINING_K)
    url = f"{API}/structures/{rig.structure_id}/alarm-rules"
    with rig.org.client("viewer") as viewer:
        before = viewer.get(url).json()
    assert before["defaults"] is False and before["cusum_design"]["modes"] == 1
    # Before any verdict, no common error is known: the design for independent records.
    assert before["cusum_design"]["threshold"] == pytest.approx(design_cusum(1460.0, 2.0).threshold)
    # A small step, a few σ̂k: no single record need prove it; the chart must add it up.
    records = [rig.upload(0.0, 7) for _ in range(3)] + [rig.upload(STEP_K, 8) for _ in range(5)]
    modes = [r["verdict"]["modes"][0] for r in records]
    # The share of σ̂k² the model's own error makes common to every record raises the threshold
    # that keeps one false alarm a year (models.alarms.in_control_arl): its median over the healthy records.
    healthy = [m for m, r in zip(modes, records, strict=True) if r["verdict"]["status"] == "healthy"]
    share = round(float(np.median([1.0 - (m["sigma_k_record"] / m["sigma_k"]) ** 2 for m in healthy])), 2)
    with rig.org.client("viewer") as viewer:
        design = viewer.get(url).json()["cusum_design"]
    assert share > 0 and design["common_share"] == share, share
    assert design["threshold"] == pytest.approx(design_cusum(1460.0, 2.0, share).threshold)
    z = np.array([m["k_hat"] / m["sigma_k"] for m in modes])
    sides = np.zeros((len(z) + 1, 2))  # Page's two-sided CUSUM by its definition, from zero
    for i, zi in enumerate(z):
        sides[i + 1] = np.maximum(0.0, sides[i] + np.array([zi, -zi]) - design["reference"])
    beyond = np.flatnonzero(sides[1:].max(axis=1) > design["threshold"])
    alarm_at = int(beyond[0]) if beyond.size else None
    assert alarm_at is not None and alarm_at > 3, f"a step the chart adds up over records: z = {z}"
    (alarm,) = rig.alarms(rule_kind="cusum")
    assert alarm["fault_mode"] == "k2" and alarm["record_id"] == records[alarm_at]["id"]
    assert alarm["drift_started_at"] is not None
    side = sides[: alarm_at + 2, int(np.argmax(sides[alarm_at + 1]))]
    started = int(np.flatnonzero(side[: alarm_at + 1] == 0.0)[-1])  # the record after the last zero
    assert when(alarm["drift_started_at"]) == T0 + started * STEP
    assert alarm["rule"]["design"]["threshold"] == pytest.approx(design["threshold"])


def test_rules_default_until_set_and_bad_rules_are_refused_with_nothing_stored(api_server: LiveServer):
    org = Org.create(api_server)
    with clients(org) as (admin, ingest, viewer):
        structure_id = create_structure(admin)["id"]
        url = f"{API}/structures/{structure_id}/alarm-rules"
        defaults = viewer.get(url).json()
        assert defaults["defaults"] is True
        assert [r["kind"] for r in defaults["rules"]] == ["persistence", "cusum", "severity"]
        assert defaults["cusum_design"]["arl_in_control"] == pytest.approx(1460.0)
        assert defaults["cusum_problem"] is None
        bad = {
            "unknown kind": [{"kind": "sprt", "k": 1}],
            "m below k": [{"kind": "persistence", "k": 4, "m": 3}],
            "negative threshold": [{"kind": "severity", "threshold": -5.0}],
            "zero false alarms": [{"kind": "cusum", "false_alarms_per_year": 0}],
            "negative shift": [{"kind": "cusum", "shift": -1.0}],
            "a shift no threshold can serve": [{"kind": "cusum", "shift": 0.05}],
            "a shift a single record decides": [{"kind": "cusum", "shift": 11.6}],
            "a kind twice": [{"kind": "severity"}, {"kind": "severity", "threshold": 3.0}],
            "no rule": [],
            "an unknown field": [{"kind": "persistence", "window": 5}],
        }
        messages = {
            "unknown kind": "persistence",
            "m below k": "at least k",
            "negative threshold": "give it positive",
            "a kind twice": "at most once",
            "a shift no threshold can serve": "threshold beyond 16 σ",
            "a shift a single record decides": "smaller shift",
        }
        for case, rules in bad.items():
            response = admin.put(url, json={"rules": rules})
            assert response.status_code == 422, f"{case}: {response.text}"
            assert messages.get(case, "") in detail(response), f"{case}: {detail(response)}"
        assert viewer.get(url).json() == defaults, "a refused rule changed the stored ones"
        wanted = [{"kind": "severity", "threshold": 12.5}]
        assert ingest.put(url, json={"rules": wanted}).status_code == 403
        assert viewer.put(url, json={"rules": wanted}).status_code == 403
        stored = admin.put(url, json={"rules": wanted})
        assert stored.status_code == 200, stored.text
        assert stored.json()["rules"] == [{"kind": "severity", "threshold": 12.5, "clear_after": 5}]
        assert stored.json()["cusum_design"] is None
        assert viewer.get(url).json() == stored.json() | {"defaults": False}


def test_alarms_are_listed_newest_first_with_filters_and_pages(rig: Rig):
    everything = rig.alarms(limit=1000)
    assert len(everything) >= 2
    assert [a["id"] for a in everything] == sorted((a["id"] for a in everything), reverse=True)
    with rig.org.client("viewer") as viewer:
        pages, cursor = [], None
        while True:
            params = {"structure_id": rig.structure_id, "limit": 1} | ({"cursor": cursor} if cursor else {})
            page = viewer.get(f"{API}/alarms", params=params).json()
            pages += page["items"]
            if (cursor := page["next_cursor"]) is None:
                break
        assert pages == everything
        assert rig.alarms(state="resolved") == everything
        assert rig.alarms(rule_kind="cusum") == []
        assert rig.alarms(end=everything[-1]["opened_at"]) == []
        assert rig.alarms(start=everything[0]["opened_at"]) == everything[:1]
        for bad in (
            {"state": "closed"},
            {"rule_kind": "sprt"},
            {"start": "2026-05-01T00:00:00"},
            {"cursor": 0},
        ):
            assert viewer.get(f"{API}/alarms", params=bad).status_code == 422, bad


def test_the_database_keeps_one_unresolved_alarm_per_structure_rule_and_fault_mode(
    database_server: LiveServer,
):
    """Whatever the code does, a second unresolved alarm of the same key is refused by the database
    (persistence alarms have no fault mode: NULL, which a plain unique index would let through)."""
    sessions = database_server.app.state.sessions
    now = utcnow()
    with clients(Org.create(database_server)) as (admin, _, _):
        structure_id = create_structure(admin, f"alarmed-{uuid.uuid4().hex[:6]}")["id"]
    with sessions() as session:
        organisation_id = session.get(Structure, structure_id).organisation_id

    def alarm(mode: str | None, state: str = "open") -> Alarm:
        return Alarm(
            structure_id=structure_id,
            organisation_id=organisation_id,
            rule_kind="persistence" if mode is None else "severity",
            rule={},
            fault_mode=mode,
            state=state,
            triggered_at=now,
            evaluated_through=now,
        )

    for mode in (None, "k2"):
        with sessions() as session:
            session.add_all([alarm(mode, "resolved"), alarm(mode, "resolved"), alarm(mode)])
            session.flush()
            session.add(alarm(mode, "acknowledged"))
            with pytest.raises(IntegrityError):
                session.flush()
            session.rollback()


def test_a_re_inspection_with_new_models_re_judges_the_record(api_server: LiveServer):
    """A k1 fault inspected by a k2 model alone is an unknown fault, without a magnitude: no
    severity alarm. Once a k1 model exists, inspecting the record again measures it, and the
    severity rule fires on the new verdict."""
    rig = new_rig(api_server, seed=63, rules=[{"kind": "severity", "threshold": 10.0}])
    with clients(rig.org) as (admin, ingest, _):
        record = simulated("k1", 20.0, [63, 1], 2000)
        body = npz_bytes(x=record.x, y=record.y, fs=record.fs)
        uploaded = post_record(ingest, rig.structure_id, body, "application/x-npz", inspect="true").json()
        assert uploaded["verdict"]["status"] == "unknown_fault" and uploaded["verdict"]["interval"] is None
        assert rig.alarms() == []
        train_fault_mode(admin, ingest, rig.structure_id, "k1", seed=64)
        response = ingest.post(f"{API}/records/{uploaded['id']}/inspect")
        assert response.status_code == 200, response.text
        verdict = response.json()
        low, high = verdict["interval"]
        assert verdict["fault_mode"] == "k1" and (high < -10.0 or low > 10.0)
    (alarm,) = rig.alarms()
    assert (alarm["rule_kind"], alarm["fault_mode"], alarm["record_id"]) == ("severity", "k1", uploaded["id"])


def test_verdicts_stored_at_once_open_one_alarm(database_server: LiveServer):
    """Six faulty records uploaded together, each firing the rule: one alarm, no error. The
    structure's evaluations run one after another (its row lock), each seeing the alarm the one
    before committed."""
    rig = new_rig(database_server, seed=65, rules=[{"kind": "persistence", "k": 1, "m": 1}])
    bodies = [simulated("k2", FAULT_K, [65, index], 2000) for index in range(6)]

    def upload(index: int) -> int:
        record = bodies[index]
        moment = (T0 + index * STEP).isoformat()
        with rig.org.client("ingest") as ingest:
            body = npz_bytes(x=record.x, y=record.y, fs=record.fs)
            response = post_record(
                ingest, rig.structure_id, body, "application/x-npz", inspect="true", acquired_at=moment
            )
        return response.status_code

    with ThreadPoolExecutor(len(bodies)) as pool:
        assert list(pool.map(upload, range(len(bodies)))) == [201] * len(bodies)
    (alarm,) = rig.alarms()
    assert alarm["state"] == "open"


def test_a_cusum_the_models_cannot_serve_does_not_run_and_says_why(api_server: LiveServer):
    """Models trained on three experiments carry an error, the same in every record, of about a
    quarter of σ̂k²: no threshold within 16 σ keeps one false alarm a year. The CUSUM then does not
    run (the structure's verdicts are stored as ever), and the rules' answer says what to change."""
    rig = new_rig(api_server, seed=68, rules=[PERSISTENCE])
    assert statuses([rig.upload(0.0, 16)]) == ["healthy"]  # the models' error, as verdicts measure it
    with clients(rig.org) as (admin, _, viewer):
        url = f"{API}/structures/{rig.structure_id}/alarm-rules"
        stored = admin.put(url, json={"rules": [{"kind": "cusum"}]})
        assert stored.status_code == 200, stored.text
        answer = viewer.get(url).json()
    assert answer["cusum_design"] is None
    assert (
        "threshold beyond 16 σ" in answer["cusum_problem"] and "more experiments" in answer["cusum_problem"]
    )
    assert statuses([rig.upload(FAULT_K, 9)]) == ["faulty"]
    assert rig.alarms(rule_kind="cusum") == []


def _rows_read(plan: dict, table: str) -> float:
    """Rows the plan's scans of ``table`` returned, over all their loops (EXPLAIN ANALYZE)."""
    own = plan["Actual Rows"] * plan["Actual Loops"] if plan.get("Relation Name") == table else 0.0
    return own + sum(_rows_read(child, table) for child in plan.get("Plans", ()))


def test_an_organisation_s_alarms_are_listed_without_reading_another_s(postgres_url):
    """Found through the organisation's structures, PostgreSQL walked every organisation's alarms
    newest first until it had a page of this one's: 142 ms for a page of 100 behind 300 000 of
    another organisation's, and growing with them. The page is read from the organisation's own
    index: the listing's plan returns a page and one from the alarms table, however many alarms
    the other organisation has (20 000 here, newer than all of this one's)."""
    from harness import migrated

    url = migrated.postgresql(postgres_url, f"alarms_{uuid.uuid4().hex}")
    engine = make_engine(url)
    with engine.begin() as connection:
        connection.execute(
            text(
                "INSERT INTO organisations (id, name, created_at) "
                "VALUES (1, 'busy', now()), (2, 'quiet', now())"
            )
        )
        connection.execute(
            text(
                "INSERT INTO structures (id, organisation_id, name, fs, description, created_at) "
                "SELECT g, CASE WHEN g <= 5 THEN 1 ELSE 2 END, 's' || g, 1500, '', now() "
                "FROM generate_series(1, 8) g"
            )
        )
        for organisation, first_structure, structures, count, start in (
            (2, 6, 3, 120, 400),
            (1, 1, 5, 20_000, 300),
        ):
            connection.execute(
                text(
                    "INSERT INTO alarms (structure_id, organisation_id, rule_kind, rule, fault_mode, state, "
                    "opened_at, triggered_at, evaluated_through) "
                    "SELECT :first + g % :structures, :organisation, 'severity', '{}', 'k' || g, 'resolved', "
                    "now() - make_interval(days => :start) + g * interval '1 second', now(), now() "
                    "FROM generate_series(1, :count) g"
                ),
                dict(
                    first=first_structure,
                    structures=structures,
                    organisation=organisation,
                    count=count,
                    start=start,
                ),
            )
        connection.execute(text("ANALYZE"))
    statements: list[tuple[str, dict]] = []

    def capture(conn, cursor, statement, parameters, context, executemany):
        statements.append((statement, parameters))

    event.listen(engine, "before_cursor_execute", capture)
    with Session(engine) as session:
        page = alarms.list_alarms(session, Principal(2, Role.viewer, 0), limit=50)
    event.remove(engine, "before_cursor_execute", capture)
    assert len(page.items) == 50 and {item.structure_id for item in page.items} <= {6, 7, 8}
    assert [item.id for item in page.items] == sorted((item.id for item in page.items), reverse=True)
    ((listing, parameters),) = [(s, p) for s, p in statements if "FROM alarms" in s and "LIMIT" in s]
    with engine.connect() as connection:
        (plan,) = connection.exec_driver_sql(
            f"EXPLAIN (ANALYZE, FORMAT JSON) {listing}", parameters
        ).scalar_one()
    assert _rows_read(plan["Plan"], "alarms") <= 51, plan
    engine.dispose()


def test_a_k_hat_at_the_model_s_range_limit_does_not_feed_its_cusum_and_the_rules_say_why(
    api_server: LiveServer,
):
    """A fault beyond the range the fault-mode model searches pins k̂ at the range's edge: where
    the search stopped, not a measurement, and z = k̂/σ̂k there is whatever the edge makes it. The
    record does not step that mode's CUSUM (which would signal on it at once), and the rules'
    answer says why; the next record measured within the range counts again."""
    rig = new_rig(api_server, seed=66, rules=[{"kind": "cusum"}], magnitudes=CUSUM_TRAINING_K)
    healthy = [rig.upload(0.0, 10) for _ in range(2)]
    beyond = rig.upload(60.0, 11)
    (mode,) = beyond["verdict"]["modes"]
    assert mode["at_range_limit"] and mode["k_hat"] == pytest.approx(32.0, abs=0.01), mode
    assert abs(mode["k_hat"] / mode["sigma_k"]) > 20, "a z the CUSUM would have signalled on at once"
    assert rig.alarms(rule_kind="cusum") == []
    url = f"{API}/structures/{rig.structure_id}/alarm-rules"
    with rig.org.client("viewer") as viewer:
        answer = viewer.get(url).json()
        assert answer["cusum_design"] is not None and answer["cusum_problem"] is None
        (reason,) = answer["cusum_skipped"].values()
        assert list(answer["cusum_skipped"]) == ["k2"] and "limit of the range" in reason, reason
    assert statuses([*healthy, rig.upload(0.0, 12)]) == ["healthy"] * 3
    with rig.org.client("viewer") as viewer:
        assert viewer.get(url).json()["cusum_skipped"] == {}


def test_a_cusum_alarm_is_resolved_when_its_rule_stops_running(api_server: LiveServer):
    """A CUSUM alarm stayed open after the rules' answer said the CUSUM does not run. Rules whose
    CUSUM the structure's models cannot serve (a false-alarm rate whose threshold, for the models'
    common error, lies beyond 16 σ) resolve it as ``rule_not_running``, announced as any
    resolution; the persistence rule's alarm, still running, stays open."""
    rules = [{"kind": "persistence", "k": 1, "m": 1}, {"kind": "cusum"}]
    rig = new_rig(api_server, seed=67, rules=rules, magnitudes=CUSUM_TRAINING_K)
    records = [rig.upload(0.0, 13), rig.upload(FAULT_K, 14)]
    assert statuses(records) == ["healthy", "faulty"]
    (cusum,) = rig.alarms(rule_kind="cusum", state="open")
    (persistence,) = rig.alarms(rule_kind="persistence", state="open")
    with rig.org.client("viewer") as viewer:
        url = f"{API}/structures/{rig.structure_id}/alarm-rules"
        share = viewer.get(url).json()["cusum_design"]["common_share"]
    # Ten times the run length the largest threshold keeps, for this share: no design; for
    # independent records (share 0: the rules' check) there is one.
    reach = in_control_arl(alarms.MAX_THRESHOLD, DESIGN_SHIFT / 2, share)
    strict = {"kind": "cusum", "false_alarms_per_year": 365 * 4.0 / (10 * reach)}
    with clients(rig.org) as (admin, _, viewer):
        stored = admin.put(url, json={"rules": [rules[0], strict]})
        assert stored.status_code == 200, stored.text
        answer = stored.json()
        assert answer["cusum_design"] is None and "threshold beyond 16 σ" in answer["cusum_problem"]
        resolved = viewer.get(f"{API}/alarms/{cusum['id']}").json()
    assert resolved["state"] == "resolved" and resolved["resolution"] == "rule_not_running"
    assert "threshold beyond 16 σ" in resolved["resolution_note"]
    assert [(t["from_state"], t["to_state"], t["by"]) for t in resolved["transitions"]] == [
        (None, "open", None),
        ("open", "resolved", None),
    ]
    assert rig.alarms(rule_kind="persistence", state="open") == [persistence]
    # Records on: the CUSUM still does not run, and opens nothing.
    assert statuses([rig.upload(FAULT_K, 15)]) == ["faulty"]
    assert rig.alarms(rule_kind="cusum", state="open") == []


def test_a_cusum_steps_only_on_records_not_localised_to_another_mode(api_server: LiveServer):
    """The demo opened a CUSUM alarm on k1 for a k2 fault: k1's model, fitted to a record the
    verdict localised to k2, also moved its k̂ (z 3–5), and its chart signalled on that. A k̂ under
    a model the verdict found not to describe the record is no evidence of that mode's drift: the
    record steps the CUSUM of the mode it is localised to alone, and the rules' answer says why."""
    rig = new_rig(api_server, seed=68, rules=[{"kind": "cusum"}], magnitudes=CUSUM_TRAINING_K)
    with clients(rig.org) as (admin, ingest, _):
        train_fault_mode(admin, ingest, rig.structure_id, "k1", seed=69, magnitudes=CUSUM_TRAINING_K)
    faulty = [rig.upload(4.0, 16 + i) for i in range(3)]
    assert [(r["verdict"]["status"], r["verdict"]["fault_mode"]) for r in faulty] == [("faulty", "k2")] * 3
    k1 = [next(m for m in r["verdict"]["modes"] if m["name"] == "k1") for r in faulty]
    assert sum(m["k_hat"] / m["sigma_k"] for m in k1) > 8, "a k1 chart stepped by these would signal"
    assert {a["fault_mode"] for a in rig.alarms(rule_kind="cusum")} == {"k2"}
    with rig.org.client("viewer") as viewer:
        skipped = viewer.get(f"{API}/structures/{rig.structure_id}/alarm-rules").json()["cusum_skipped"]
    assert list(skipped) == ["k1"] and "localised to fault mode 'k2'" in skipped["k1"], skipped
