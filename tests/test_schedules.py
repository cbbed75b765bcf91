"""Schedules: the API, the due-time arithmetic, and a due time run exactly once however many
sweepers look (embedded threads, `narxwatch worker` processes, Procrastinate's periodic sweep)."""

from __future__ import annotations

import datetime as dt
import time
import uuid
from pathlib import Path

import pytest
from api_helpers import (
    API,
    Org,
    clients,
    create_structure,
    detail,
    simulated,
    train_fault_mode,
    upload_simulated,
    verdicts,
    wait_for,
)
from live import LiveServer
from sqlalchemy import select, text
from workers import workers

from service.config import Settings
from service.db import make_engine, session_factory, transaction
from service.domain import schedules
from service.domain.schedules import RUN_SCHEDULE, following
from service.jobs import embedded
from service.migrate import upgrade_database
from service.tables import Job, Organisation, Schedule, Structure

T0 = dt.datetime(2026, 11, 21, 10, 7, 30, tzinfo=dt.UTC)


def schedules_url(structure_id: int) -> str:
    return f"{API}/structures/{structure_id}/schedules"


# --- due times ------------------------------------------------------------------------------


def test_an_interval_schedule_steps_by_whole_intervals_and_runs_once_for_what_it_missed():
    step = 600
    assert following(None, step, T0, T0) == T0 + dt.timedelta(seconds=step)
    # Down for 3.5 intervals: one run now, the next due on the original grid.
    late = T0 + dt.timedelta(seconds=3.5 * step)
    assert following(None, step, T0, late) == T0 + dt.timedelta(seconds=4 * step)
    exactly = T0 + dt.timedelta(seconds=2 * step)
    assert following(None, step, T0, exactly) == T0 + dt.timedelta(seconds=3 * step)


def test_a_cron_schedule_runs_at_the_next_matching_minute_in_utc():
    assert following("*/15 * * * *", None, T0, T0) == T0.replace(minute=15, second=0)
    assert following("0 3 * * 1", None, T0, T0) == dt.datetime(2026, 11, 23, 3, 0, tzinfo=dt.UTC)  # a Monday


# --- the sweep, on a SQLite file ------------------------------------------------------------


@pytest.fixture
def database(tmp_path: Path):
    url = f"sqlite:///{tmp_path / 'schedules.db'}"
    upgrade_database(url)
    sessions = session_factory(make_engine(url))
    with transaction(sessions) as session:
        organisation = Organisation(name="sweep")
        session.add(organisation)
        session.flush()
        structure = Structure(organisation_id=organisation.id, name="rig", fs=1500.0)
        session.add(structure)
        session.flush()
        session.add(
            Schedule(
                structure_id=structure.id, action="inspect_pending", interval_seconds=600, next_run_at=T0
            )
        )
    return url, sessions


def run_schedule_jobs(sessions) -> list[dict]:
    with sessions() as session:
        return [job.args for job in session.scalars(select(Job).where(Job.task == RUN_SCHEDULE))]


def test_a_due_time_is_deferred_once_however_often_it_is_swept(database):
    _, sessions = database
    later = T0 + dt.timedelta(seconds=1)
    with sessions() as session:

        def sweep(now: dt.datetime) -> int:  # as the job runners do: each sweep committed
            deferred = schedules.sweep(session, embedded.defer, now=now)
            session.commit()
            return deferred

        assert sweep(T0 - dt.timedelta(seconds=1)) == 0
        assert sweep(later) == 1
        assert sweep(later) == 0
        schedule = session.get(Schedule, 1)
        assert schedule is not None
        assert schedule.next_run_at == T0 + dt.timedelta(seconds=600) and schedule.last_run_at == later
    assert run_schedule_jobs(sessions) == [{"schedule_id": 1, "due_at": T0.isoformat()}]


# --- the API ----------------------------------------------------------------------------------


def test_schedules_are_created_listed_and_deleted(tenant):
    sid = create_structure(tenant.admin)["id"]
    before = dt.datetime.now(dt.UTC)
    interval = tenant.admin.post(
        schedules_url(sid), json={"action": "inspect_pending", "interval_seconds": 3600}
    )
    assert interval.status_code == 201, interval.text
    first = dt.datetime.fromisoformat(interval.json()["next_run_at"])
    assert before <= first <= dt.datetime.now(dt.UTC), "an interval schedule is first due at once"
    cron = tenant.admin.post(schedules_url(sid), json={"action": "reinspect_latest", "cron": "0 3 * * *"})
    assert cron.status_code == 201, cron.text
    due = dt.datetime.fromisoformat(cron.json()["next_run_at"])
    assert (due.hour, due.minute, due.second) == (3, 0, 0) and due > before
    listed = tenant.viewer.get(schedules_url(sid)).json()
    assert [s["id"] for s in listed] == [interval.json()["id"], cron.json()["id"]]
    assert tenant.admin.delete(f"{schedules_url(sid)}/{cron.json()['id']}").status_code == 204
    assert [s["id"] for s in tenant.viewer.get(schedules_url(sid)).json()] == [interval.json()["id"]]
    gone = tenant.admin.delete(f"{schedules_url(sid)}/{cron.json()['id']}")
    assert gone.status_code == 404 and "schedule" in detail(gone)


BAD_SCHEDULES = [
    ({"action": "inspect_pending"}, "exactly one of interval_seconds and cron"),
    ({"action": "inspect_pending", "interval_seconds": 60, "cron": "* * * * *"}, "exactly one"),
    ({"action": "inspect_pending", "interval_seconds": 5}, "greater than or equal to 10"),
    ({"action": "inspect_pending", "interval_seconds": "60"}, "valid integer"),
    ({"action": "inspect_pending", "cron": "*/5 * * *"}, "five fields"),
    ({"action": "inspect_pending", "cron": "61 * * * *"}, "cron expression"),
    ({"action": "inspect_pending", "cron": "0 0 30 2 *"}, "ever runs"),
    ({"action": "retrain", "interval_seconds": 60}, "inspect_pending"),
    (
        {"action": "inspect_pending", "cron": "0 * * * *", "first_run_at": "2027-01-01T00:00:00Z"},
        "first_run_at",
    ),
    (
        {"action": "inspect_pending", "interval_seconds": 60, "first_run_at": "2027-01-01T00:00:00"},
        "timezone",
    ),
]


@pytest.mark.parametrize(("body", "message"), BAD_SCHEDULES)
def test_a_bad_schedule_is_refused_with_its_reason_and_stores_nothing(tenant, body, message):
    sid = create_structure(tenant.admin)["id"]
    response = tenant.admin.post(schedules_url(sid), json=body)
    assert response.status_code == 422 and message in detail(response), response.text
    assert tenant.viewer.get(schedules_url(sid)).json() == []


def test_only_admins_change_schedules(tenant):
    sid = create_structure(tenant.admin)["id"]
    body = {"action": "inspect_pending", "interval_seconds": 60}
    for client in (tenant.ingest, tenant.viewer):
        assert client.post(schedules_url(sid), json=body).status_code == 403
    created = tenant.admin.post(schedules_url(sid), json=body).json()
    assert tenant.ingest.delete(f"{schedules_url(sid)}/{created['id']}").status_code == 403
    assert len(tenant.viewer.get(schedules_url(sid)).json()) == 1


# --- three workers, one job -----------------------------------------------------------------


@pytest.fixture(params=["sqlite", "postgresql"])
def empty_database(request, tmp_path: Path) -> str:
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'three.db'}"
    import postgres

    return postgres.create_database(request.getfixturevalue("postgres_url"), f"three_{uuid.uuid4().hex[:12]}")


def run_schedule_count(database_url: str, schedule_id: int) -> int:
    """Jobs made for the schedule, read from the backend's own queue table."""
    table, task = (
        ("jobs", "task") if database_url.startswith("sqlite") else ("procrastinate_jobs", "task_name")
    )
    of_schedule = "CAST(args->>'schedule_id' AS INTEGER) = :id"
    query = f"SELECT count(*) FROM {table} WHERE {task} = 'run_schedule' AND {of_schedule}"
    engine = make_engine(database_url)
    with engine.connect() as connection:
        count = connection.execute(text(query), {"id": schedule_id}).scalar_one()
    engine.dispose()
    return count


def test_three_workers_run_a_due_schedule_once(empty_database: str, tmp_path: Path):
    """Three `narxwatch worker` processes (embedded on SQLite, Procrastinate on PostgreSQL) all
    sweep; a schedule due once gives one job, and its records one verdict each."""
    settings = Settings(database_url=empty_database, embedded_worker=False)
    with LiveServer(settings) as server, workers(empty_database, 3, tmp_path) as running:
        org = Org.create(server)
        with clients(org) as (admin, ingest, viewer):
            sid = create_structure(admin)["id"]
            train_fault_mode(admin, ingest, sid, "k2", seed=81)
            pending = [upload_simulated(ingest, sid, simulated("k2", 12.0, [82, i]))["id"] for i in range(3)]
            due = dt.datetime.now(dt.UTC) + dt.timedelta(seconds=3)  # all three workers are up by then
            body = {"action": "inspect_pending", "interval_seconds": 3600, "first_run_at": due.isoformat()}
            schedule = admin.post(schedules_url(sid), json=body).json()

            def inspected() -> bool:
                return {v["record_id"] for v in verdicts(viewer, sid)} >= set(pending)

            wait_for(inspected, 60, "the scheduled inspection left records without a verdict")
            time.sleep(5)  # two more sweeps of every worker: room for a duplicate to show
            found = verdicts(viewer, sid)
        assert all(worker.alive() for worker in running), [w.output()[-2000:] for w in running]
    assert sorted(v["record_id"] for v in found if v["record_id"] in pending) == pending
    assert run_schedule_count(empty_database, schedule["id"]) == 1
