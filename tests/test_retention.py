"""Retention on both databases: each organisation's policy, the pruning in bounded batches, and
what stays exact through it.

Records are uploaded through the API, acquired days before ``NOW``; their verdicts are written
as the inspection writes them (a row, then ``fleet.count_verdict`` on the structure's state),
which needs no trained model. What a pruning should do is worked out from the rows beforehand,
in Python, and compared with what the tables hold after; ``/metrics``, the summaries and the
state rows are compared with ``COUNT(*)`` and with each structure's history walked
(``test_fleet_scale``'s checks).
"""

from __future__ import annotations

import datetime as dt
import os
import threading
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path

import httpx
import pytest
from sqlalchemy import Engine, insert, select
from sqlalchemy.orm import Session, sessionmaker

from harness.api_helpers import API, Org, clients, create_structure, detail, json_body, post_record, wait_for
from harness.cli import invoke
from harness.dashboard_helpers import DASHBOARD, logged_in
from harness.fleet import FUTURE, STATUSES, Fleet, counted, kept, scraped, walked
from models.inspection import ModeResult
from service.db import session_factory, transaction
from service.domain import fleet, retention
from service.jobs import embedded
from service.tables import (
    Delivery,
    ModelVersion,
    Organisation,
    Record,
    Refinement,
    RefinementRecord,
    Structure,
    Verdict,
    Webhook,
    utcnow,
)

NOW = utcnow()
DAY = dt.timedelta(days=1)
MODE = asdict(ModeResult("k2", 1.5, 0.2, 0.2, 7.5, True, 1e-3, 30.0, 40.0, 0.3, True, False))


@dataclass
class Site:
    fleet: Fleet
    url: str
    sessions: sessionmaker[Session]


@pytest.fixture(scope="module")
def site(fleet_server: Fleet) -> Site:
    """A server of its own per database, as ``test_fleet_scale``'s, with the test's sessions on it."""
    url = fleet_server.engine.url.render_as_string(hide_password=False)
    return Site(fleet_server, url, session_factory(fleet_server.engine))


# --- building a history ---------------------------------------------------------------------


def stored(ingest: httpx.Client, structure_id: int, days_ago: float, seed: int) -> dict:
    acquired_at = NOW - days_ago * DAY
    response = post_record(
        ingest, structure_id, json_body(2000, seed=seed, acquired_at=acquired_at.isoformat())
    )
    assert response.status_code == 201, response.text
    return response.json()


def judged(site: Site, record: dict, *statuses: str) -> list[int]:
    """Verdicts of ``statuses`` on a stored record, each under a model set of its own, written
    with the state's update as the inspection writes them."""
    ids = []
    with transaction(site.sessions) as session:
        acquired_at = dt.datetime.fromisoformat(record["acquired_at"])
        for index, status in enumerate(statuses):
            values = dict(
                record_id=record["id"], structure_id=record["structure_id"], acquired_at=acquired_at,
                model_set=f"k2:{index}", status=status, fault_detected=status != "healthy",
                fault_mode="k2" if status == "faulty" else None, alpha=0.05, lags=40, n_samples=2000,
                z_critical=1.96, q_critical_detection=40.0, detected_by=[], modes=[MODE],
            )  # fmt: skip
            verdict_id = session.execute(insert(Verdict).returning(Verdict.id), values).scalar_one()
            fleet.count_verdict(session, verdict_id, record["structure_id"], acquired_at, status, utcnow())
            ids.append(verdict_id)
    return ids


def history(
    site: Site, ingest: httpx.Client, structure_id: int, plan: list[tuple[float, tuple[str, ...]]]
) -> None:
    for days_ago, statuses in plan:
        judged(
            site,
            stored(ingest, structure_id, days_ago, seed=hash((structure_id, days_ago)) % 2**32),
            *statuses,
        )


def organisation_id(site: Site, org: Org) -> int:
    with site.sessions() as session:
        return session.scalar(select(Organisation.id).where(Organisation.name == org.name))


def rows(engine: Engine, org: Org) -> dict[str, object]:
    """An organisation's records (id → signals pruned, and the blobs' sizes) and verdict ids."""
    with engine.connect() as connection:
        of_org = select(Structure.id).join(Organisation).where(Organisation.name == org.name)
        records = connection.execute(
            select(Record.id, Record.acquired_at, Record.signals_pruned_at, Record.x, Record.y).where(
                Record.structure_id.in_(of_org)
            )
        ).all()
        verdicts = connection.execute(
            select(Verdict.id, Verdict.record_id, Verdict.acquired_at).where(Verdict.structure_id.in_(of_org))
        ).all()
    return {
        "records": {
            r.id: (r.acquired_at, r.signals_pruned_at is not None, len(r.x), len(r.y)) for r in records
        },
        "verdicts": {v.id: (v.record_id, v.acquired_at) for v in verdicts},
    }


def expected(before: dict, signal_days: int | None, verdict_days: int | None) -> dict:
    """What a policy leaves of ``rows``, worked out from them alone."""
    signals = NOW - signal_days * DAY if signal_days is not None else None
    verdicts = NOW - verdict_days * DAY if verdict_days is not None else None
    kept_verdicts = {
        vid: (rid, at) for vid, (rid, at) in before["verdicts"].items() if verdicts is None or at >= verdicts
    }
    with_verdicts = {rid for rid, _ in kept_verdicts.values()}
    records = {}
    for rid, (at, pruned, nx, ny) in before["records"].items():
        drop = pruned or (signals is not None and at < signals)
        if verdicts is not None and at < verdicts and drop and rid not in with_verdicts:
            continue
        records[rid] = (at, True, 0, 0) if drop else (at, False, nx, ny)
    return {"records": records, "verdicts": kept_verdicts}


def assert_exact(site: Site, org: Org, *structure_ids: int) -> None:
    """``/metrics``, each state row and each summary agree with what the tables hold."""
    assert scraped(site.fleet.server) == counted(site.fleet.engine)
    with clients(org) as (_, _, viewer):
        for structure_id in structure_ids:
            walk = walked(site.fleet.engine, structure_id)
            assert kept(site.fleet.engine, structure_id) == walk, structure_id
            summary = viewer.get(f"{API}/structures/{structure_id}/summary").json()
            assert summary["counts"] == {status: walk[status] for status in STATUSES}
            assert summary["total"] == sum(walk[status] for status in STATUSES)


# --- the pruning ----------------------------------------------------------------------------

# (days before NOW, statuses of the record's verdicts)
SPANNING = [  # faulty since 70.5 days ago (the second verdict then): a run across the horizon of 60
    (100.5, ("healthy",)), (70.5, ("unknown_fault", "faulty")), (65.5, ("faulty",)), (50.5, ("faulty",)),
    (40.5, ()), (20.5, ("faulty", "faulty")), (10.5, ("faulty",)), (1.5, ("faulty",)),
]  # fmt: skip
OLD = [(90.5, ("healthy",)), (80.5, ()), (61.5, ("faulty", "healthy"))]  # all past 60 days, latest too


def test_pruning_takes_what_the_policy_says_and_keeps_every_count_exact(site: Site):
    org, other = Org.create(site.fleet.server), Org.create(site.fleet.server)
    with clients(org) as (admin, ingest, _), clients(other) as (other_admin, other_ingest, _):
        spanning = create_structure(admin, "spanning")["id"]
        old = create_structure(admin, "old")["id"]
        history(site, ingest, spanning, SPANNING)
        history(site, ingest, old, OLD)
        theirs = create_structure(other_admin, "theirs")["id"]
        history(site, other_ingest, theirs, SPANNING)  # pruned only when its organisation is
        response = admin.put(f"{API}/retention", json={"signal_days": 30, "verdict_days": 60})
        assert response.status_code == 200, response.text
        assert response.json()["defaults"] is False

    assert_exact(site, org, spanning, old)
    assert kept(site.fleet.engine, spanning)["since"] == NOW - 70.5 * DAY
    before, before_other = rows(site.fleet.engine, org), rows(site.fleet.engine, other)
    with site.sessions() as session:
        pruned = retention.prune(session, organisation_id(site, org), now=NOW)
    after = rows(site.fleet.engine, org)

    assert after == expected(before, 30, 60)
    assert rows(site.fleet.engine, other) == before_other
    gone = before["verdicts"].keys() - after["verdicts"].keys()
    assert (pruned.signals, pruned.verdicts, pruned.records) == (
        sum(1 for at, *_ in before["records"].values() if at < NOW - 30 * DAY),
        len(gone),
        len(before["records"]) - len(after["records"]),
    )
    assert (pruned.signals, len(gone), pruned.records) == (8, 7, 6)  # the plans: not a vacuous comparison
    assert_exact(site, org, spanning, old)
    assert_exact(site, other, theirs)
    assert kept(site.fleet.engine, old)["status"] is None  # its whole history past the horizon
    assert kept(site.fleet.engine, spanning)["since"] == NOW - 50.5 * DAY  # the run now starts later

    with site.sessions() as session:  # a second pruning finds nothing more
        again = retention.prune(session, organisation_id(site, org), now=NOW)
    assert (again.signals, again.verdicts, again.records, again.batches) == (0, 0, 0, 0)


def test_a_verdict_from_the_future_stands_neither_when_the_latest_nor_when_the_run_is_pruned(site: Site):
    """Each structure also holds a healthy verdict dated 9999-12-31 (its record stored before
    acquisition times were checked), counted as the inspection counts it now: never the latest.
    Pruning one whose other verdicts are all past the horizon leaves it uninspected, not healthy
    since 9999; pruning the start of another's faulty run starts the run later, the healthy
    verdict after it notwithstanding."""
    org = Org.create(site.fleet.server)
    with clients(org) as (admin, ingest, _):
        gone = create_structure(admin, "gone")["id"]
        spanning = create_structure(admin, "spanning")["id"]
        history(site, ingest, gone, OLD)
        history(site, ingest, spanning, [(70.5, ("faulty",)), (1.5, ("faulty",))])
        assert admin.put(f"{API}/retention", json={"signal_days": 30, "verdict_days": 60}).status_code == 200
    for structure_id in (gone, spanning):
        with transaction(site.sessions) as session:
            values = dict(structure_id=structure_id, fs=1500.0, n_samples=3, acquired_at=FUTURE,
                          sha256=uuid.uuid4().hex * 2, x=b"", y=b"")  # fmt: skip
            record_id = session.execute(insert(Record).returning(Record.id), values).scalar_one()
            fleet.count_record(session, structure_id)
        judged(
            site,
            {"id": record_id, "structure_id": structure_id, "acquired_at": FUTURE.isoformat()},
            "healthy",
        )
    assert_exact(site, org, gone, spanning)
    assert (kept(site.fleet.engine, spanning)["status"], kept(site.fleet.engine, spanning)["since"]) == (
        "faulty",
        NOW - 70.5 * DAY,
    )
    with site.sessions() as session:
        retention.prune(session, organisation_id(site, org), now=NOW)
    assert_exact(site, org, gone, spanning)
    assert kept(site.fleet.engine, gone)["status"] is None and kept(site.fleet.engine, gone)["healthy"] == 1
    assert kept(site.fleet.engine, spanning)["since"] == NOW - 1.5 * DAY


def test_batches_are_bounded_and_uploads_go_on_between_them(site: Site):
    org = Org.create(site.fleet.server)
    with clients(org) as (admin, ingest, _):
        sid = create_structure(admin)["id"]
        history(site, ingest, sid, [(100.5 + i, ("healthy",)) for i in range(7)])
        assert admin.put(f"{API}/retention", json={"signal_days": 30, "verdict_days": 60}).status_code == 200
        batches: list[tuple[str, int]] = []

        def between(batch: retention.Batch) -> None:
            batches.append((batch.what, batch.rows))
            # Committed: an upload goes through at once, and is not pruned (acquired now).
            stored(ingest, sid, 0, seed=1000 + len(batches))

        with site.sessions() as session:
            pruned = retention.prune(session, organisation_id(site, org), now=NOW, batch=2, progress=between)
    assert batches == [(what, n) for what in ("signals", "verdicts", "records") for n in (2, 2, 2, 1)]
    assert pruned.batches == 12
    assert len(rows(site.fleet.engine, org)["records"]) == 12  # the uploads made between batches
    assert_exact(site, org, sid)


def logged(site: Site, admin: httpx.Client, plan: list[tuple[float, str]]) -> tuple[int, dict[int, tuple]]:
    """A webhook of the caller's organisation and its delivery log, as the outbox writes it, of
    (days before NOW, status) rows. Its address is never called: no delivery is due this year."""
    body = {"url": "https://93.184.215.14/hooks", "secret": "s" * 32, "events": ["alarm.opened"]}
    response = admin.post(f"{API}/webhooks", json=body)
    assert response.status_code == 201, response.text
    webhook = response.json()["id"]
    log = {}
    with transaction(site.sessions) as session:
        organisation = session.scalar(select(Webhook.organisation_id).where(Webhook.id == webhook))
        for days_ago, status in plan:
            written = NOW - days_ago * DAY
            values = dict(
                organisation_id=organisation, webhook_id=webhook, key=str(uuid.uuid4()), event="alarm.opened",
                payload={"alarm": days_ago}, status=status, attempts=0 if status == "pending" else 1,
                next_attempt_at=NOW + 365 * DAY, created_at=written,
                delivered_at=written if status == "delivered" else None,
            )  # fmt: skip
            delivery = session.execute(insert(Delivery).returning(Delivery.id), values).scalar_one()
            log[delivery] = (days_ago, status)
    return webhook, log


def listed(admin: httpx.Client, webhook: int) -> set[int]:
    response = admin.get(f"{API}/webhooks/{webhook}/deliveries", params={"limit": 100})
    assert response.status_code == 200, response.text
    return {item["id"] for item in response.json()["items"]}


def test_settled_deliveries_go_with_the_verdicts_they_announced_and_owed_ones_stay(site: Site):
    """The delivery log is kept as long as the verdicts: settled deliveries (delivered, failed)
    written before the verdict horizon are deleted, in batches; pending ones, which the outbox still
    owes, never are; nor another organisation's."""
    plan = [(90.5, "delivered"), (80.5, "failed"), (75.5, "pending"), (70.5, "delivered"), (61.5, "failed")]
    plan += [(59.5, "delivered"), (30.5, "failed"), (1.5, "pending")]
    org, other = Org.create(site.fleet.server), Org.create(site.fleet.server)
    with clients(org) as (admin, _, _), clients(other) as (other_admin, _, _):
        webhook, log = logged(site, admin, plan)
        other_webhook, other_log = logged(site, other_admin, plan)
        assert listed(admin, webhook) == log.keys() and listed(other_admin, other_webhook) == other_log.keys()
        assert admin.put(f"{API}/retention", json={"signal_days": 30, "verdict_days": 60}).status_code == 200

        batches: list[tuple[str, int]] = []
        with site.sessions() as session:
            pruned = retention.prune(
                session,
                organisation_id(site, org),
                now=NOW,
                batch=3,
                progress=lambda b: batches.append((b.what, b.rows)),
            )
        owed_or_recent = {d for d, (days_ago, status) in log.items() if status == "pending" or days_ago < 60}
        assert listed(admin, webhook) == owed_or_recent
        assert len(log) - len(owed_or_recent) == 4  # the plan: not a vacuous comparison
        assert (pruned.deliveries, batches) == (4, [("deliveries", 3), ("deliveries", 1)])
        assert listed(other_admin, other_webhook) == other_log.keys()


def test_records_a_refinement_names_outlive_their_verdicts(site: Site):
    """A refinement's report names the records it was fitted and judged on: they lose their
    signals and verdicts with the others, never their rows."""
    org = Org.create(site.fleet.server)
    with clients(org) as (admin, ingest, _):
        sid = create_structure(admin)["id"]
        fitted, judged_whole, plain = (stored(ingest, sid, 100.5 + i, seed=500 + i) for i in range(3))
        for record in (fitted, judged_whole, plain):
            judged(site, record, "healthy")
        assert admin.put(f"{API}/retention", json={"signal_days": 30, "verdict_days": 60}).status_code == 200
    with transaction(site.sessions) as session:  # as a refinement stores it (service.domain.refinements)
        base = ModelVersion(
            structure_id=sid, kind="baseline", name="baseline", version=1,
            document={}, training={}, statistics={}, active=False,
        )  # fmt: skip
        session.add(base)
        session.flush()
        session.add(
            Refinement(
                structure_id=sid, record_id=fitted["id"], base_model_id=base.id, report={},
                records=[
                    RefinementRecord(record_id=fitted["id"], role="estimation", position=0),
                    RefinementRecord(record_id=judged_whole["id"], role="test", position=0),
                ],
            )
        )  # fmt: skip
    with site.sessions() as session:
        pruned = retention.prune(session, organisation_id(site, org), now=NOW)
    left = rows(site.fleet.engine, org)
    assert set(left["records"]) == {fitted["id"], judged_whole["id"]}
    assert all(pruned_signals for _, pruned_signals, *_ in left["records"].values())
    assert left["verdicts"] == {}
    assert (pruned.signals, pruned.verdicts, pruned.records) == (3, 3, 1)
    assert_exact(site, org, sid)


def test_a_verdict_stored_while_its_record_is_pruned_is_counted_once(site: Site):
    """An inspection of an old record commits while a pruning wants to delete the record: the
    pruning waits for it (PostgreSQL: at the structure's state row, then sees the verdict and keeps
    the record; SQLite: at the writer lock, then prunes both) and every count stays exact."""
    org = Org.create(site.fleet.server)
    with clients(org) as (admin, ingest, _):
        sid = create_structure(admin)["id"]
        record = stored(ingest, sid, 100.5, seed=900)
        assert admin.put(f"{API}/retention", json={"signal_days": 30, "verdict_days": 60}).status_code == 200
    inspecting = site.sessions()
    acquired_at = dt.datetime.fromisoformat(record["acquired_at"])
    values = dict(
        record_id=record["id"], structure_id=sid, acquired_at=acquired_at, model_set="k2:late",
        status="faulty", fault_detected=True, fault_mode="k2", alpha=0.05, lags=40, n_samples=2000,
        z_critical=1.96, q_critical_detection=40.0, detected_by=[], modes=[MODE],
    )  # fmt: skip
    verdict_id = inspecting.execute(insert(Verdict).returning(Verdict.id), values).scalar_one()
    fleet.count_verdict(inspecting, verdict_id, sid, acquired_at, "faulty", utcnow())
    pruned: list[retention.Pruned] = []

    def pruning() -> None:
        with site.sessions() as session:
            pruned.append(retention.prune(session, organisation_id(site, org), now=NOW))

    worker = threading.Thread(target=pruning)
    worker.start()
    worker.join(1.0)
    assert worker.is_alive()  # waiting for the inspection's transaction
    inspecting.commit()
    inspecting.close()
    worker.join(30)
    assert not worker.is_alive() and pruned
    left = rows(site.fleet.engine, org)
    if site.fleet.engine.dialect.name == "postgresql":
        assert left["verdicts"] == {verdict_id: (record["id"], acquired_at)}
        assert left["records"][record["id"]][1] is True  # its signals pruned all the same
    else:
        assert left == {"records": {}, "verdicts": {}}
    assert_exact(site, org, sid)


BAD = [
    ({"signal_days": 0, "verdict_days": 30}, "greater than or equal to 1"),
    ({"signal_days": -5, "verdict_days": 30}, "greater than or equal to 1"),
    ({"signal_days": 30, "verdict_days": 36_501}, "less than or equal to 36500"),
    ({"signal_days": 90, "verdict_days": 30}, "must not exceed verdict_days"),
    ({"signal_days": None, "verdict_days": 30}, "must not exceed verdict_days"),
    ({"signal_days": "30", "verdict_days": 60}, "valid integer"),
    ({"signal_days": 1.5, "verdict_days": 60}, "valid integer"),
    ({"signal_days": 30}, "verdict_days"),
    ({"signal_days": 30, "verdict_days": 60, "records": 5}, "Extra inputs"),
]


def test_a_policy_is_read_and_set_by_admins_and_bad_ones_are_refused(site: Site):
    org = Org.create(site.fleet.server)
    with clients(org) as (admin, ingest, viewer):
        defaults = admin.get(f"{API}/retention").json()
        assert defaults == {
            "signal_days": retention.DEFAULT_SIGNAL_DAYS,
            "verdict_days": retention.DEFAULT_VERDICT_DAYS,
            "defaults": True,
            "last_pruned_at": None,
        }
        for body, reason in BAD:
            response = admin.put(f"{API}/retention", json=body)
            assert response.status_code == 422, body
            assert reason in detail(response), (body, detail(response))
            assert admin.get(f"{API}/retention").json() == defaults
        for client in (ingest, viewer):
            assert (
                client.put(f"{API}/retention", json={"signal_days": 1, "verdict_days": 2}).status_code == 403
            )
            assert client.get(f"{API}/retention").status_code == 403
        forever = admin.put(f"{API}/retention", json={"signal_days": 7, "verdict_days": None})
        assert forever.status_code == 200, forever.text
        assert admin.get(f"{API}/retention").json() == forever.json()
        assert forever.json()["verdict_days"] is None and forever.json()["defaults"] is False


def test_a_record_whose_signals_are_pruned_says_so_in_the_api_and_on_its_page(site: Site):
    org = Org.create(site.fleet.server)
    with clients(org) as (admin, ingest, _):
        sid = create_structure(admin)["id"]
        body = json_body(2000, seed=77, acquired_at=(NOW - 200 * DAY).isoformat())
        record = post_record(ingest, sid, body).json()
        judged(site, record, "faulty")
        with site.sessions() as session:  # the defaults: signals 90 days, verdicts 730
            retention.prune(session, organisation_id(site, org), now=NOW)

        again = post_record(ingest, sid, body)  # the same data: the stored record, which says so
        assert again.status_code == 200, again.text
        assert dt.datetime.fromisoformat(again.json()["signals_pruned_at"]) >= NOW
        training = admin.post(f"{API}/structures/{sid}/models/baseline", json={"record_ids": [record["id"]]})
        assert training.status_code == 409, training.text
        assert f"signals of record {record['id']} were pruned on" in detail(training)
        assert "retention" in detail(training)

    with logged_in(site.fleet.server, org.keys["viewer"]) as browser:
        page = browser.get(f"{DASHBOARD}/records/{record['id']}")
    assert page.status_code == 200, page.text
    assert 'id="signals-pruned"' in page.text and "under the organisation's retention" in page.text
    assert 'id="verdict"' in page.text  # the verdict stands
    assert 'id="chart-response"' not in page.text


def test_the_sweep_queues_one_pruning_a_period_and_the_cli_prunes_at_once(site: Site, tmp_path: Path):
    """Last in the file: the sweep prunes every organisation of the database."""
    queued_org, cli_org = Org.create(site.fleet.server), Org.create(site.fleet.server)
    structures = {}
    for org in (queued_org, cli_org):
        with clients(org) as (admin, ingest, _):
            structures[org.name] = create_structure(admin)["id"]
            history(site, ingest, structures[org.name], [(100.5 + i, ()) for i in range(3)])
            assert (
                admin.put(f"{API}/retention", json={"signal_days": 30, "verdict_days": None}).status_code
                == 200
            )

    env = {**os.environ, "NARXWATCH_DATABASE_URL": site.url}
    result = invoke("db", "prune", "--org", cli_org.name, "--batch", "2", cwd=tmp_path, environ=env)
    assert result.stdout.count(f"{cli_org.name}: 2 records' signals dropped") == 1
    assert f"{cli_org.name}: 1 records' signals dropped" in result.stdout
    assert (
        "3 records' signals dropped, 0 verdicts deleted, 0 records deleted, 0 deliveries deleted, "
        "in 2 batch(es)" in result.stdout
    )
    assert all(row[1] for row in rows(site.fleet.engine, cli_org)["records"].values())
    assert not any(row[1] for row in rows(site.fleet.engine, queued_org)["records"].values())

    later = utcnow() + 2 * DAY  # every organisation is due a day after it was created
    with site.sessions() as session:
        assert retention.sweep(session, embedded.defer, DAY, later) >= 2
        assert retention.sweep(session, embedded.defer, DAY, later) == 0  # claimed for this period
    wait_for(
        lambda: all(row[1] for row in rows(site.fleet.engine, queued_org)["records"].values()),
        30,
        "the queued pruning",
    )
    # The sweep queued every organisation's pruning: the counts are exact once none is running,
    # and this organisation's may have been pruned while another's still runs.
    wait_for(lambda: _idle(site.fleet.engine), 30, "the other organisations' prunings")
    assert_exact(site, queued_org, structures[queued_org.name])
    with clients(queued_org) as (admin, _, _):
        assert admin.get(f"{API}/retention").json()["last_pruned_at"] is not None


def test_vacuum_gives_the_space_of_pruned_signals_back(site: Site, tmp_path: Path):
    """After the sweep above has pruned every organisation's old signals."""
    sqlite = site.fleet.engine.dialect.name == "sqlite"
    files = [Path(site.fleet.engine.url.database + suffix) for suffix in ("", "-wal")] if sqlite else []

    def size() -> int:
        return sum(f.stat().st_size for f in files if f.exists())

    before = size()
    env = {**os.environ, "NARXWATCH_DATABASE_URL": site.url}
    assert "vacuumed" in invoke("db", "vacuum", cwd=tmp_path, environ=env).stdout
    if sqlite:  # dozens of records' signals of 32 KB each were pruned
        assert size() < before - 500_000, (before, size())
    else:
        with site.fleet.engine.connect() as connection:
            vacuumed = connection.exec_driver_sql(
                "SELECT last_vacuum IS NOT NULL FROM pg_stat_user_tables WHERE relname = 'records'"
            ).scalar_one()
        assert vacuumed


def _idle(engine) -> bool:
    jobs = counted(engine)["jobs"]
    return jobs["queued"] == jobs["running"] == 0  # type: ignore[index]
