"""Schedules: the API, the due-time arithmetic, a due time run exactly once however many
sweepers look (embedded threads, `narxwatch worker` processes, Procrastinate's periodic sweep),
and a run that neither one bad record nor one bad schedule can stop.

The API over HTTP on SQLite: what it checks is the service's, and a run on PostgreSQL's queue is
the three workers'. The sweeps' claims, runs and times on both databases."""

from __future__ import annotations

import datetime as dt
import uuid
from pathlib import Path

import pytest
from sqlalchemy import func, select, text, update

from harness import migrated
from harness.api_helpers import (
    API,
    Org,
    clients,
    create_structure,
    detail,
    jobs_ended,
    simulated,
    train_fault_mode,
    upload_simulated,
    verdicts,
    wait_for,
)
from harness.job_helpers import EXACT_TERM_NAMES, LONG_LAG_TERMS, TOO_SHORT, Monitored, database_url
from harness.live import LiveServer
from harness.workers import Worker, workers
from models.signals import minimum_samples
from service.config import Settings
from service.db import make_engine, session_factory, transaction
from service.domain import schedules
from service.domain.schedules import RETRY_UNSWEPT, RUN_SCHEDULE, following
from service.jobs import embedded
from service.jobs.tasks import INSPECT_RECORD
from service.tables import (
    InspectionFailure,
    Job,
    ModelVersion,
    Organisation,
    Record,
    Schedule,
    Structure,
    Verdict,
)

T0 = dt.datetime(2026, 11, 21, 10, 7, 30, tzinfo=dt.UTC)
# `narxwatch worker` processes on PostgreSQL: Procrastinate's sweeps every second (the setting;
# the default is 2 s), so that a due schedule waits less for its run.
SWEEP_EVERY_SECOND = {"worker_sweep_seconds": "1"}


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
    url = migrated.sqlite(tmp_path / "schedules.db")
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


@pytest.fixture(params=["sqlite", "postgresql"])
def monitored(request, tmp_path: Path) -> Monitored:
    """A structure with an active k2 model on either database, and its job backend."""
    return Monitored.create(database_url(request.param, tmp_path, request), EXACT_TERM_NAMES)


def add_schedule(monitored: Monitored, due: dt.datetime, cron: str | None = None) -> int:
    with transaction(monitored.sessions) as session:
        schedule = Schedule(
            structure_id=monitored.structure_id,
            action="inspect_pending",
            interval_seconds=None if cron else 600,
            cron=cron,
            next_run_at=due,
        )
        session.add(schedule)
        session.flush()
        return schedule.id


def test_two_sweepers_that_both_read_a_schedule_as_due_defer_one_job(monitored: Monitored):
    """The stale read the compare-and-set exists for: both sweepers have read the due time before
    either writes; the second one's claim finds the time moved on and defers nothing."""
    schedule_id = add_schedule(monitored, T0)
    backend = monitored.backend()
    now = T0 + dt.timedelta(seconds=1)
    with monitored.sessions() as first, monitored.sessions() as second:
        (read_by_first,) = schedules.due_schedules(first, now)
        (read_by_second,) = schedules.due_schedules(second, now)
        assert read_by_first == read_by_second and read_by_first.schedule_id == schedule_id
        assert schedules.claim(first, backend.defer, read_by_first, now) is True
        assert schedules.claim(second, backend.defer, read_by_second, now) is False
    assert run_schedule_count(monitored.settings.database_url, schedule_id) == 1


def test_a_schedule_that_cannot_be_swept_holds_up_neither_other_schedules_nor_the_jobs(monitored: Monitored):
    """A cron expression the database holds but croniter refuses (written by hand, or by an older
    release): the sweep logs it, tries it again a minute later, sweeps the next schedule, and the
    worker still runs the queued jobs."""
    broken = add_schedule(monitored, T0, cron="* * * * *")
    with transaction(monitored.sessions) as session:
        session.execute(update(Schedule).where(Schedule.id == broken).values(cron="every tuesday"))
    healthy = add_schedule(monitored, T0)
    record_id = monitored.store("k2", 12.0, [83])
    backend = monitored.backend()
    organisation = monitored.principal.organisation_id
    with transaction(monitored.sessions) as session:
        backend.defer(session, INSPECT_RECORD, organisation, record_id=record_id)
    before = dt.datetime.now(dt.UTC)
    with monitored.sessions() as session:
        assert schedules.sweep(session, backend.defer) == 1  # the healthy one
    backend.work(once=True)  # the embedded worker sweeps too: nothing is due any more
    with monitored.sessions() as session:
        verdicts_of_record = select(func.count()).select_from(Verdict).where(Verdict.record_id == record_id)
        assert session.scalar(verdicts_of_record) == 1
        jobs = backend.list_jobs(session, organisation, None, 10, None)
        assert sorted((job.task, job.state) for job in jobs) == [
            (INSPECT_RECORD, "done"),
            (RUN_SCHEDULE, "done"),
        ]
        assert [job.args["schedule_id"] for job in jobs if job.task == RUN_SCHEDULE] == [healthy]
        postponed = session.get(Schedule, broken)
        assert postponed is not None
        assert before + RETRY_UNSWEPT <= postponed.next_run_at <= dt.datetime.now(dt.UTC) + RETRY_UNSWEPT


@pytest.mark.parametrize("kind", ["sqlite", "postgresql"])
def test_a_record_the_models_cannot_inspect_is_marked_and_the_rest_of_the_run_goes_on(
    request, tmp_path: Path, kind: str
):
    """An inspect_pending run over a record too short for the model's lags, between valid ones:
    the valid records get their verdicts, the bad one is marked with why and with which model
    set, the run's job succeeds, and a new model set tries the record again."""
    monitored = Monitored.create(database_url(kind, tmp_path, request), LONG_LAG_TERMS)
    before = set(monitored.record_ids())  # the training records
    valid_first = monitored.store("k2", 12.0, [84, 0])
    bad = monitored.store("none", 0.0, [84, 1], n=TOO_SHORT)
    valid_last = monitored.store("k2", -12.0, [84, 2])
    schedule_id = add_schedule(monitored, T0)
    backend = monitored.backend()
    organisation = monitored.principal.organisation_id
    with monitored.sessions() as session:
        assert schedules.sweep(session, backend.defer) == 1
    backend.work(once=True)
    with monitored.sessions() as session:
        inspected = set(session.scalars(select(Verdict.record_id)))
        assert {valid_first, valid_last} <= inspected and bad not in inspected
        (failure,) = session.scalars(select(InspectionFailure))
        (model_id,) = session.scalars(select(ModelVersion.id).where(ModelVersion.active))
        assert (failure.record_id, failure.model_set) == (bad, str(model_id))
        needed = minimum_samples(monitored.settings.lags, 100)  # the model reaches back 100 samples
        assert "too short" in failure.reason and f"at least {needed}" in failure.reason
        (run,) = backend.list_jobs(session, organisation, None, 10, None)
        assert (run.task, run.args["schedule_id"], run.state, run.attempts) == (
            RUN_SCHEDULE,
            schedule_id,
            "done",
            1,
        )
    assert before <= inspected
    # New models: the record is tried again, and marked again under the new model set.
    new_model = monitored.train(LONG_LAG_TERMS, seed=2)
    with transaction(monitored.sessions) as session:
        backend.defer(session, RUN_SCHEDULE, organisation, schedule_id=schedule_id, due_at=T0.isoformat())
    backend.work(once=True)
    with monitored.sessions() as session:
        marks = session.execute(select(InspectionFailure.record_id, InspectionFailure.model_set)).all()
        assert sorted(marks) == sorted([(bad, str(model_id)), (bad, str(new_model))])


# --- the API ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def api_server(sqlite_api_server: LiveServer) -> LiveServer:
    return sqlite_api_server


def test_schedules_are_created_listed_and_deleted(tenant):
    sid = create_structure(tenant.admin)["id"]
    train_fault_mode(tenant.admin, tenant.ingest, sid, "k2", seed=85)
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


def test_a_schedule_on_a_structure_without_active_models_is_refused(tenant):
    """It would have nothing to inspect with, and be skipped at every run without a word."""
    sid = create_structure(tenant.admin)["id"]
    response = tenant.admin.post(
        schedules_url(sid), json={"action": "inspect_pending", "interval_seconds": 60}
    )
    assert response.status_code == 409, response.text
    assert "no active fault-mode model" in detail(response) and "/models/fault-modes" in detail(response)
    assert tenant.viewer.get(schedules_url(sid)).json() == []


def test_a_scheduled_run_over_a_record_the_models_cannot_inspect_still_inspects_the_others(tenant):
    """The finding end to end, on the service's own workers: records stored with inspect=false,
    one too short for the model's lags, then an inspect_pending schedule. Its run succeeds, the
    records after the bad one get their verdicts, and the bad one none."""
    sid = create_structure(tenant.admin)["id"]
    train_fault_mode(tenant.admin, tenant.ingest, sid, "k2", seed=92, terms=LONG_LAG_TERMS)
    bad = upload_simulated(tenant.ingest, sid, simulated("none", 0.0, [93], TOO_SHORT))["id"]
    valid = [upload_simulated(tenant.ingest, sid, simulated("k2", 8.0, [94, i]))["id"] for i in range(2)]
    body = {"action": "inspect_pending", "interval_seconds": 3600}
    assert tenant.admin.post(schedules_url(sid), json=body).status_code == 201

    def ran() -> list[dict]:
        return [j for j in tenant.admin.get(f"{API}/jobs").json()["items"] if j["task"] == RUN_SCHEDULE]

    wait_for(lambda: [j["state"] for j in ran()] == ["done"], 60, "the schedule's run did not succeed")
    inspected = {v["record_id"] for v in verdicts(tenant.viewer, sid)}
    assert set(valid) <= inspected and bad not in inspected
    assert tenant.admin.get(f"{API}/jobs", params={"state": "failed"}).json()["items"] == []


def test_only_admins_change_schedules(tenant):
    sid = create_structure(tenant.admin)["id"]
    train_fault_mode(tenant.admin, tenant.ingest, sid, "k2", seed=86)
    body = {"action": "inspect_pending", "interval_seconds": 60}
    for client in (tenant.ingest, tenant.viewer):
        assert client.post(schedules_url(sid), json=body).status_code == 403
    created = tenant.admin.post(schedules_url(sid), json=body).json()
    assert tenant.ingest.delete(f"{schedules_url(sid)}/{created['id']}").status_code == 403
    assert len(tenant.viewer.get(schedules_url(sid)).json()) == 1


# --- three workers, one job -----------------------------------------------------------------


@pytest.fixture(params=["sqlite", "postgresql"])
def empty_database(request, tmp_path: Path) -> str:
    """A new database holding nothing, at the newest revision."""
    if request.param == "sqlite":
        return migrated.sqlite(tmp_path / "three.db")
    return migrated.postgresql(request.getfixturevalue("postgres_url"), f"three_{uuid.uuid4().hex[:12]}")


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
    sweep; a schedule due once gives one job, and its records one verdict each. (Two sweepers
    that both read it as due are the domain's test above: one claim wins.)"""
    settings = Settings(database_url=empty_database, embedded_worker=False)
    # The workers first: their start-up goes on while the server starts and the model is trained.
    with (
        workers(empty_database, 3, tmp_path, **SWEEP_EVERY_SECOND) as running,
        LiveServer(settings) as server,
    ):
        org = Org.create(server)
        with clients(org) as (admin, ingest, viewer):
            sid = create_structure(admin)["id"]
            train_fault_mode(admin, ingest, sid, "k2", seed=81)
            pending = [upload_simulated(ingest, sid, simulated("k2", 12.0, [82, i]))["id"] for i in range(3)]
            wait_for(lambda: all(sweeping(worker) for worker in running), 60, "the workers never came up")
            body = {"action": "inspect_pending", "interval_seconds": 3600}  # due now
            schedule = admin.post(schedules_url(sid), json=body).json()

            def inspected() -> bool:
                return {v["record_id"] for v in verdicts(viewer, sid)} >= set(pending)

            wait_for(inspected, 60, "the scheduled inspection left records without a verdict")
            # Every job ended: none is left to make a verdict, and a second run of the schedule,
            # had a sweep deferred one, is in the queue's table by now.
            wait_for(lambda: jobs_ended(admin), 60, "jobs still waiting or running")
            found = verdicts(viewer, sid)
        if empty_database.startswith("postgresql"):
            wait_for(lambda: swept_a_second_apart(empty_database), 30, "no two sweeps a second apart")
        assert all(worker.alive() for worker in running), [w.output()[-2000:] for w in running]
    assert sorted(v["record_id"] for v in found if v["record_id"] in pending) == pending
    assert run_schedule_count(empty_database, schedule["id"]) == 1


def swept_a_second_apart(database_url: str) -> bool:
    """Procrastinate's periodic deferrer queued the schedules' sweep for two consecutive seconds
    (its jobs carry the second they were due at): the workers sweep at the period they were
    given, not at the default's even seconds."""
    query = (
        "SELECT DISTINCT CAST(args->>'timestamp' AS BIGINT) FROM procrastinate_jobs "
        "WHERE task_name = 'sweep_schedules'"
    )
    engine = make_engine(database_url)
    with engine.connect() as connection:
        seconds = set(connection.execute(text(query)).scalars())
    engine.dispose()
    return any(second + 1 in seconds for second in seconds)


@pytest.mark.parametrize("seconds", [0, 7, 61])
def test_a_sweep_period_that_is_not_a_divisor_of_a_minute_is_refused(seconds: int):
    """Procrastinate's cron of seconds restarts each minute: a period of 7 s would sweep 4 s
    apart across each minute's end."""
    with pytest.raises(ValueError, match="worker_sweep_seconds"):
        Settings(worker_sweep_seconds=seconds)
    assert Settings(worker_sweep_seconds=60).worker_sweep_seconds == 60


def sweeping(worker: Worker) -> bool:
    """The worker has started its loop (it says so as it starts it)."""
    return "running jobs" in worker.output()


@pytest.mark.parametrize("kind", ["sqlite", "postgresql"])
def test_reinspect_latest_takes_the_latest_record_acquired_up_to_now(request, tmp_path: Path, kind: str):
    """A record stored with a date in the future (before such dates were refused) is not the
    structure's latest: the run inspects the newest record acquired up to the server's clock."""
    monitored = Monitored.create(database_url(kind, tmp_path, request), EXACT_TERM_NAMES)
    present = monitored.store("k2", 12.0, [85, 0])
    future = monitored.store("none", 0.0, [85, 1])
    with transaction(monitored.sessions) as session:
        year_9999 = dt.datetime(9999, 12, 31, tzinfo=dt.UTC)
        session.execute(update(Record).where(Record.id == future).values(acquired_at=year_9999))
    schedule_id = add_schedule(monitored, T0)
    with transaction(monitored.sessions) as session:
        session.execute(update(Schedule).where(Schedule.id == schedule_id).values(action="reinspect_latest"))
    backend = monitored.backend()
    with monitored.sessions() as session:
        assert schedules.sweep(session, backend.defer) == 1
    backend.work(once=True)
    with monitored.sessions() as session:
        inspected = set(session.scalars(select(Verdict.record_id)))
    assert present in inspected and future not in inspected
