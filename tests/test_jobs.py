"""Queued inspections (embedded job backend): 202 now, the verdict later, exactly once.

Through HTTP on SQLite and PostgreSQL for the user's view of a queued job (a refused mode, never
queued, on SQLite alone); on a real SQLite file for the queue's own rules (leases and their
renewal, redelivery, retries with backoff); on both databases for errors that no retry can mend,
which fail a job at once.
"""

from __future__ import annotations

import datetime as dt
import os
import subprocess
import threading
import time
from pathlib import Path

import pytest
from sqlalchemy import event, func, select, text, update

from harness import migrated
from harness.api_helpers import (
    API,
    Org,
    clients,
    create_structure,
    detail,
    json_body,
    nothing_written,
    npz_bytes,
    post_record,
    simulated,
    train_fault_mode,
    verdicts_of,
    wait_for,
)
from harness.cli import NARXWATCH, invoke
from harness.job_helpers import EXACT_TERM_NAMES, LONG_LAG_TERMS, TOO_SHORT, Monitored, database_url
from harness.live import LiveServer
from harness.workers import workers
from models.fnarx import FNARX
from models.inspection import inspect
from service.config import Settings
from service.db import make_engine, session_factory, transaction
from service.domain import records, structures
from service.domain.schedules import RUN_SCHEDULE
from service.jobs.embedded import FIRST_RETRY, LEASE, MAX_ATTEMPTS, EmbeddedBackend, claim, defer, run
from service.jobs.tasks import INSPECT_RECORD, TASKS
from service.schemas import StructureCreate
from service.security import Principal, Role
from service.tables import InspectionFailure, Job, ModelVersion, Organisation, Record, Verdict, utcnow


def test_a_queued_upload_answers_202_and_its_verdict_appears_once(database_server: LiveServer):
    """The queued verdict is the one an immediate inspection gives: checked against a twin
    structure, trained identically, that inspects the same record with inspect=true."""
    org = Org.create(database_server)
    with clients(org) as (admin, ingest, viewer):
        sid, twin = create_structure(admin)["id"], create_structure(admin)["id"]
        for structure_id in (sid, twin):
            train_fault_mode(admin, ingest, structure_id, "k2", seed=71)
        record = simulated("k2", 25.0, [72])
        body = npz_bytes(x=record.x, y=record.y, fs=record.fs)
        immediate = post_record(ingest, twin, body, "application/x-npz", inspect="true").json()["verdict"]
        response = post_record(ingest, sid, body, "application/x-npz", inspect="queue")
        assert response.status_code == 202, response.text
        answer = response.json()
        assert answer["verdict"] is None and answer["created"] is True
        deadline = time.monotonic() + 30
        while not (found := verdicts_of(viewer, sid, answer["id"])) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert len(found) == 1, "the queued inspection produced no verdict within 30 s"
        for field in ("status", "fault_detected", "fault_mode", "k_hat", "sigma_k", "interval", "modes"):
            assert found[0][field] == immediate[field], field
        # Inspecting again with the same models returns that verdict: no second one.
        again = ingest.post(f"{API}/records/{answer['id']}/inspect")
        assert again.status_code == 200 and again.json()["id"] == found[0]["id"]
        assert len(verdicts_of(viewer, sid, answer["id"])) == 1


def test_an_unknown_inspect_mode_is_refused_and_stores_nothing(sqlite_api_server: LiveServer):
    org = Org.create(sqlite_api_server)
    with clients(org) as (admin, ingest, _):
        sid = create_structure(admin)["id"]
        with nothing_written(org, sid):
            response = post_record(ingest, sid, json_body(300), inspect="later")
            assert response.status_code == 422, response.text
            assert "inspect" in detail(response) and "'queue'" in detail(response)


# --- the queue's rules, on a SQLite file -----------------------------------------------------


@pytest.fixture
def queue(tmp_path: Path):
    """A migrated database with one structure (no models yet), one stored record and a job to
    inspect it."""
    url = migrated.sqlite(tmp_path / "jobs.db")
    sessions = session_factory(make_engine(url))
    with transaction(sessions) as session:
        organisation = Organisation(name="jobs")
        session.add(organisation)
        session.flush()
        principal = Principal(organisation.id, Role.admin, key_id=0)
        structure = structures.create_structure(session, principal, StructureCreate(name="rig", fs=1500.0))
        record = simulated("none", 0.0, [73])
        stored, _ = records.store_record(session, structure, record.x, record.y, structure.fs, None)
        defer(session, INSPECT_RECORD, organisation.id, record_id=stored.id)
    return sessions, Settings(database_url=url, embedded_worker=False)


def test_a_leased_job_is_not_claimed_twice_until_its_lease_runs_out(queue):
    sessions, _ = queue
    with sessions() as session:
        first = claim(session)
        assert first is not None and first.attempts == 1
        assert claim(session) is None, "a leased job was handed to a second worker"
        # Its worker died: once the lease has run out, the job is redelivered.
        later = utcnow() + LEASE + dt.timedelta(seconds=1)
        again = claim(session, now=later)
        assert again is not None and (again.id, again.attempts) == (first.id, 2)


def test_a_failing_job_is_retried_with_backoff_then_marked_failed(tmp_path: Path):
    """An error that is not final (here a record whose stored signal cannot be read) is retried."""
    monitored = Monitored.create(migrated.sqlite(tmp_path / "retry.db"), EXACT_TERM_NAMES)
    sessions, settings = monitored.sessions, monitored.settings
    damaged = monitored.store("none", 0.0, [73])
    with transaction(sessions) as session:
        session.execute(update(Record).where(Record.id == damaged).values(x=b"not an npy array"))
        defer(session, INSPECT_RECORD, monitored.principal.organisation_id, record_id=damaged)
    with sessions() as session:
        now = utcnow()
        for attempt in range(1, MAX_ATTEMPTS + 1):
            job = claim(session, now=now)
            assert job is not None and job.attempts == attempt
            run(session, job, settings, now=now)
            row = session.get(Job, job.id)
            session.refresh(row)
            assert (row.last_error or "").startswith("ValueError: "), row.last_error
            if attempt < MAX_ATTEMPTS:
                delay = FIRST_RETRY * 2 ** (attempt - 1)
                assert row.status == "queued" and row.run_after == now + delay
                assert claim(session, now=now) is None, "retried before its backoff"
                now = row.run_after + dt.timedelta(milliseconds=1)
        assert row.status == "failed" and row.finished_at is not None
        assert claim(session, now=now + dt.timedelta(days=1)) is None
        assert session.scalar(select(func.count()).select_from(Verdict)) == 0


def test_narxwatch_worker_runs_what_a_service_without_jobs_queued(tmp_path: Path):
    """NARXWATCH_EMBEDDED_WORKER=false: the service only queues; `narxwatch worker --once` (another process)
    inspects, and its verdict is the one `models.inspection.inspect` computes here from the record's
    signals and the stored model document, without the service."""
    url = f"sqlite:///{tmp_path / 'narxwatch.db'}"
    with LiveServer(Settings(database_url=url, embedded_worker=False)) as server:
        org = Org.create(server)
        with clients(org) as (admin, ingest, viewer):
            sid = create_structure(admin)["id"]
            train_fault_mode(admin, ingest, sid, "k2", seed=74)
            record = simulated("none", 0.0, [75])
            body = npz_bytes(x=record.x, y=record.y, fs=record.fs)
            queued = post_record(ingest, sid, body, "application/x-npz", inspect="queue")
            assert queued.status_code == 202, queued.text
            # The job is still queued when the worker comes (its start-up takes seconds, far
            # longer than an embedded worker, woken by the upload, needs): "ran 1 job(s)" and no
            # verdict before it, where an embedded worker would have left it none to run.
            assert verdicts_of(viewer, sid, queued.json()["id"]) == []
            result = subprocess.run(
                [NARXWATCH, "worker", "--once"],
                env={**os.environ, "NARXWATCH_DATABASE_URL": url},
                capture_output=True,
                text=True,
                timeout=120,
            )
            assert result.returncode == 0 and "ran 1 job(s)" in result.stdout, result.stderr
            (verdict,) = verdicts_of(viewer, sid, queued.json()["id"])
        engine = make_engine(url)
        with session_factory(engine)() as session:
            document = session.scalars(select(ModelVersion.document).where(ModelVersion.active)).one()
        engine.dispose()
        expected = inspect(
            record.x,
            record.y,
            [FNARX.from_document(document)],
            alpha=server.settings.alpha,
            lags=server.settings.lags,
        )
        assert (verdict["status"], verdict["fault_mode"], verdict["n_samples"]) == (
            expected.status,
            expected.fault_mode,
            expected.n_samples,
        )
        assert verdict["k_hat"] == pytest.approx(expected.k_hat, rel=1e-9)
        assert verdict["sigma_k"] == pytest.approx(expected.sigma_k, rel=1e-9)
        (mode,) = verdict["modes"]
        (expected_mode,) = expected.modes
        assert (mode["q"], mode["p_value"]) == pytest.approx(
            (expected_mode.q, expected_mode.p_value), rel=1e-9
        )


def test_narxwatch_worker_refuses_concurrency_on_the_embedded_backend(tmp_path: Path):
    """A refusal of the command's options: through its entry point in this process (the process
    itself is the test above's)."""
    environ = {**os.environ, "NARXWATCH_DATABASE_URL": f"sqlite:///{tmp_path / 'w.db'}"}
    result = invoke("worker", "--once", "--concurrency", "2", cwd=tmp_path, check=False, environ=environ)
    assert result.returncode != 0
    assert "--concurrency applies to the distributed backend" in result.stdout + result.stderr


# --- errors no retry can mend, on both databases ----------------------------------------------


@pytest.fixture(params=["sqlite", "postgresql"])
def long_lags(request, tmp_path: Path) -> Monitored:
    """A structure whose active k2 model has a term lagged 100 samples."""
    return Monitored.create(database_url(request.param, tmp_path, request), LONG_LAG_TERMS)


def test_a_job_whose_error_is_final_fails_at_once_with_its_reason(long_lags: Monitored):
    """A stored record too short for the model's lags cannot be inspected however often it is
    tried: its job fails after one attempt, saying why, and the record is marked with the model set."""
    short = long_lags.store("none", 0.0, [5], n=TOO_SHORT)
    backend = long_lags.backend()
    organisation = long_lags.principal.organisation_id
    with transaction(long_lags.sessions) as session:
        job_id = backend.defer(session, INSPECT_RECORD, organisation, record_id=short)
    backend.work(once=True)
    with long_lags.sessions() as session:
        job = backend.get_job(session, organisation, job_id)
        assert job is not None
        assert (job.state, job.attempts) == ("failed", 1), job
        assert job.error is not None and "InputError" in job.error and "too short" in job.error
        (failure,) = session.scalars(select(InspectionFailure))
        (model_id,) = session.scalars(select(ModelVersion.id).where(ModelVersion.active))
        assert (failure.record_id, failure.model_set) == (short, str(model_id))
        assert "too short" in failure.reason
        assert backend.get_job(session, organisation + 1, job_id) is None, "another organisation's job"


def test_a_queued_inspection_reads_the_active_models_once(long_lags: Monitored):
    """The job read the structure's active versions, then the inspection read them again: two
    queries where one gives the models it inspects with and the model set a refusal is marked under."""
    ids = [long_lags.store("none", 0.0, [8, i], n=TOO_SHORT) for i in range(2)]
    backend = long_lags.backend()
    organisation = long_lags.principal.organisation_id
    engine = long_lags.sessions.kw["bind"]
    reads: list[str] = []

    def count(conn, cursor, statement: str, *args) -> None:
        if statement.lstrip().upper().startswith("SELECT") and "FROM model_versions" in statement:
            reads.append(statement)

    for record_id in ids:  # the first parses the model (kept once parsed); the second is counted
        reads.clear()
        with transaction(long_lags.sessions) as session:
            backend.defer(session, INSPECT_RECORD, organisation, record_id=record_id)
        event.listen(engine, "before_cursor_execute", count)
        try:
            backend.work(once=True)
        finally:
            event.remove(engine, "before_cursor_execute", count)
    assert len(reads) == 1, reads
    with long_lags.sessions() as session:
        (model_id,) = session.scalars(select(ModelVersion.id).where(ModelVersion.active))
        marks = session.execute(select(InspectionFailure.record_id, InspectionFailure.model_set)).all()
        assert sorted(marks) == [(record_id, str(model_id)) for record_id in ids]


def test_a_job_whose_error_is_not_final_is_queued_again_with_its_reason(long_lags: Monitored):
    """A record whose stored signal cannot be read (damaged storage, perhaps mended later): the job
    is tried again after a backoff, and says why it failed meanwhile."""
    damaged = long_lags.store("none", 0.0, [6])
    with transaction(long_lags.sessions) as session:
        session.execute(update(Record).where(Record.id == damaged).values(x=b"not an npy array"))
    backend = long_lags.backend()
    organisation = long_lags.principal.organisation_id
    with transaction(long_lags.sessions) as session:
        job_id = backend.defer(session, INSPECT_RECORD, organisation, record_id=damaged)
    backend.work(once=True)  # runs what is due now: not the retry, due after the backoff
    with long_lags.sessions() as session:
        job = backend.get_job(session, organisation, job_id)
        assert job is not None and (job.state, job.attempts) == ("queued", 1), job
        assert (job.error or "").startswith("ValueError: "), job.error
        assert session.scalar(select(func.count()).select_from(InspectionFailure)) == 0


# --- a running job keeps its lease --------------------------------------------------------------


def test_a_job_running_longer_than_its_lease_is_not_claimed_by_another_worker(queue, monkeypatch):
    """The lease is renewed while the job runs: a second worker that looks once two leases have
    gone by since the claim (its first and a renewal's) finds nothing to claim, and the job
    starts once."""
    sessions, settings = queue
    lease = dt.timedelta(seconds=1.5)  # renewed every 0.5 s: a second of slack on a busy machine
    started, release = threading.Event(), threading.Event()
    starts: list[int] = []

    def long_task(session, settings, record_id: int) -> None:  # a job that takes as long as the test says
        starts.append(record_id)
        started.set()
        release.wait(30)

    monkeypatch.setitem(TASKS, INSPECT_RECORD, long_task)
    worker = EmbeddedBackend(sessions, settings, run_in_process=False, lease=lease)
    running = threading.Thread(target=worker.run_due)
    running.start()
    try:
        assert started.wait(30), "the job never started"
        with sessions() as session:
            first_lease_ends = session.scalars(select(Job.locked_until)).one()
        # Two leases after the claim: without its renewals the job would have been free a lease.
        time.sleep(max(0.0, (first_lease_ends + lease - utcnow()).total_seconds()))
        with sessions() as session:
            assert claim(session, lease=lease) is None, "a running job was handed to a second worker"
            (job,) = session.scalars(select(Job))
            assert job.status == "running" and job.locked_until > utcnow()
    finally:
        release.set()
        running.join(30)
    with sessions() as session:
        (job,) = session.scalars(select(Job))
        assert (job.status, job.attempts) == ("done", 1)
    assert len(starts) == 1


@pytest.mark.parametrize("kind", ["sqlite", "postgresql"])
def test_an_organisation_s_backlog_does_not_hold_up_another_s_jobs(request, tmp_path: Path, kind: str):
    """Fair share: six jobs of one organisation queued, then two of another, and one `narxwatch
    worker` (embedded on SQLite, Procrastinate on PostgreSQL) takes them in turn, the first of
    each then the second of each, not the second organisation's after all six of the first's.
    (The jobs are runs of schedules deleted since, which end at once.)"""
    flooding = Monitored.create(database_url(kind, tmp_path, request))
    with transaction(flooding.sessions) as session:
        other = Organisation(name="other")
        session.add(other)
        session.flush()
        organisations = [flooding.principal.organisation_id] * 6 + [other.id] * 2
        backend = flooding.backend()
        for number, organisation in enumerate(organisations):
            backend.defer(
                session, RUN_SCHEDULE, organisation, schedule_id=10_000 + number, due_at=utcnow().isoformat()
            )
    started = (
        "SELECT organisation_id FROM jobs WHERE status = 'done' ORDER BY finished_at"
        if kind == "sqlite"
        else "SELECT CAST(j.args->>'organisation_id' AS INTEGER) FROM procrastinate_events e "
        "JOIN procrastinate_jobs j ON j.id = e.job_id "
        "WHERE e.type = 'started' AND j.task_name = 'run_schedule' ORDER BY e.id"
    )

    def run_order() -> list[int]:
        with flooding.sessions() as session:
            return list(session.scalars(text(started)))

    with workers(flooding.settings.database_url, 1, tmp_path) as running:
        wait_for(lambda: len(run_order()) == len(organisations), 60, "the worker did not run every job")
        assert all(worker.alive() for worker in running)
    first, second = flooding.principal.organisation_id, other.id
    assert run_order() == [first, second, first, second, first, first, first, first]
