"""Faults on real PostgreSQL: a worker killed in the middle of a job, the database stopped and
restarted under load, and the same record uploaded twice at once."""

from __future__ import annotations

import collections
import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import psycopg
import pytest

from harness import migrated, postgres
from harness.api_helpers import (
    API,
    Org,
    clients,
    create_structure,
    jobs_ended,
    json_body,
    npz_bytes,
    post_record,
    simulated,
    train_fault_mode,
    verdicts,
    verdicts_of,
    wait_for,
)
from harness.live import LiveServer, http_client
from harness.workers import Worker, workers
from service.config import Settings
from service.jobs.distributed import conninfo
from service.migrate import upgrade_database

# A worker silent for 3 s is stalled, and the sweep that runs its jobs again looks every second.
FAST_FAILOVER = {
    "worker_heartbeat_seconds": "0.5",
    "worker_stalled_seconds": "3",
    "worker_sweep_seconds": "1",
}


@pytest.fixture
def database(postgres_url: str) -> str:
    return migrated.postgresql(postgres_url, f"faults_{uuid.uuid4().hex[:12]}")


def test_a_job_whose_worker_is_killed_mid_run_runs_again_and_leaves_one_verdict(
    database: str, tmp_path: Path
):
    settings = Settings(database_url=database, worker_heartbeat_seconds=0.5, worker_stalled_seconds=3)
    # Started first: its start-up goes on while the server starts and the model is trained.
    victim = Worker(database, tmp_path / "victim.log", **FAST_FAILOVER)
    with LiveServer(settings) as server:
        org = Org.create(server)
        with clients(org) as (admin, ingest, viewer):
            sid = create_structure(admin)["id"]
            train_fault_mode(admin, ingest, sid, "k2", seed=91)
            record = simulated("k2", 18.0, [92])
            body = npz_bytes(x=record.x, y=record.y, fs=record.fs)
            with psycopg.connect(conninfo(database)) as blocker:
                # Held until the worker is dead: its job stops at its first look at the verdicts.
                blocker.execute("LOCK TABLE verdicts IN ACCESS EXCLUSIVE MODE")
                queued = post_record(ingest, sid, body, "application/x-npz", inspect="queue")
                assert queued.status_code == 202, queued.text
                record_id = queued.json()["id"]
                with psycopg.connect(conninfo(database), autocommit=True) as look:
                    wait_for(lambda: waiting_on_verdicts(look), 30, "the job never reached the verdicts")
                    # The rescuer starts as the victim dies: its start-up goes on while the
                    # victim's missed heartbeats add up to a stall.
                    with workers(database, 1, tmp_path, **FAST_FAILOVER):
                        victim.kill()
                        blocker.rollback()
                        wait_for(lambda: inspections_ended(look), 60, "the job did not run again")
                assert len(verdicts_of(viewer, sid, record_id)) == 1
            found = verdicts_of(viewer, sid, record_id)
            immediate = ingest.post(f"{API}/records/{record_id}/inspect").json()
            assert immediate["id"] == found[0]["id"], "inspecting again made a second verdict"
    with psycopg.connect(conninfo(database)) as connection:
        starts = connection.execute(
            "SELECT count(*) FROM procrastinate_events e JOIN procrastinate_jobs j ON j.id = e.job_id "
            "WHERE j.task_name = 'inspect_record' AND e.type = 'started'"
        ).fetchone()
    assert starts == (2,), "the killed job should have started twice: once killed, once to the end"


def waiting_on_verdicts(look: psycopg.Connection) -> bool:
    """A session waits for a lock on the verdicts table: the job, blocked inside its run."""
    query = "SELECT count(*) FROM pg_locks WHERE NOT granted AND relation = 'verdicts'::regclass"
    return look.execute(query).fetchone() != (0,)


def inspections_ended(look: psycopg.Connection) -> bool:
    """Every inspection job has ended: none is left to make a verdict."""
    query = (
        "SELECT count(*) FROM procrastinate_jobs "
        "WHERE task_name = 'inspect_record' AND status IN ('todo', 'doing')"
    )
    return look.execute(query).fetchone() == (0,)


def registered_workers(database_url: str) -> int:
    """The Procrastinate workers running on the database: registered, and heard from within
    the time after which a silent one is stalled (a worker that stopped when the database did
    leaves its row until it is pruned)."""
    query = (
        "SELECT count(*) FROM procrastinate_workers WHERE last_heartbeat > now() - make_interval(secs => %s)"
    )
    with psycopg.connect(conninfo(database_url), autocommit=True) as look:
        return look.execute(query, (float(FAST_FAILOVER["worker_stalled_seconds"]),)).fetchone()[0]


STOP_MODES = ["fast", "immediate"]  # an operator's stop, and a crash
RETRY_PAUSE = 0.1  # seconds an uploading client waits after a 503


@dataclass
class Restartable:
    """A durable PostgreSQL server with the app and two workers on it, and a trained structure."""

    database: postgres.Server
    server: LiveServer
    workers: list[Worker]
    org: Org
    structure_id: int


@pytest.fixture(scope="module")
def restartable(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Restartable]:
    """One for both ways of stopping it: each test stops and restarts the server, and ends when
    every upload it acknowledged is inspected, the workers alive; its uploads and verdicts are
    its own records'."""
    with postgres.postgres_instance("restart", durable=True) as database:
        if database is None:
            pytest.skip(f"PostgreSQL unavailable: {postgres.missing_reason()}")
        folder = tmp_path_factory.mktemp("restart")
        with (
            LiveServer(Settings(database_url=database.url)) as server,
            workers(database.url, 2, folder, **FAST_FAILOVER) as running,
        ):
            org = Org.create(server)
            with clients(org) as (admin, ingest, _):
                sid = create_structure(admin)["id"]
                train_fault_mode(admin, ingest, sid, "k2", seed=93)
            yield Restartable(database, server, running, org, sid)


@pytest.fixture
def restarted(restartable: Restartable) -> Iterator[Restartable]:
    """``restartable``, running again after the test: one that failed while it was down does not
    fail the next."""
    yield restartable
    if not (restartable.database.data / "postmaster.pid").exists():
        restartable.database.start()


@pytest.mark.parametrize("stop_mode", STOP_MODES)
def test_postgresql_stopped_and_restarted_under_load_loses_no_acknowledged_upload(
    restarted: Restartable, stop_mode: str
):
    """While the database is down (stopped by an operator, or crashed) the API says so (503 on
    /readyz and on writes, never a 500); it recovers by itself, and every upload it acknowledged
    (202) is stored and inspected."""
    database, server = restarted.database, restarted.server
    org, sid = restarted.org, restarted.structure_id
    with clients(org) as (_, ingest, viewer):
        acknowledged: list[int] = []
        answers: collections.Counter[int] = collections.Counter()
        stop = threading.Event()
        # Records of their own: one the other stop mode's test stored would be answered 200.
        first_seed = STOP_MODES.index(stop_mode) * 10**7

        def upload(thread: int) -> None:
            with org.client("ingest") as client:
                for seed in range(first_seed + thread * 10**6, first_seed + (thread + 1) * 10**6):
                    if stop.is_set():
                        return
                    response = post_record(client, sid, json_body(600, seed=seed), inspect="queue")
                    answers[response.status_code] += 1
                    if response.status_code == 202:
                        acknowledged.append(response.json()["id"])
                    elif response.status_code == 503:
                        # Told the service is unavailable, a client tries again a moment later:
                        # answering a thousand 503s while it is down adds CPU, not a case.
                        stop.wait(RETRY_PAUSE)

        # Both workers running (their start-up takes seconds; after a restart, their loop's):
        # what the stop interrupts is their work, not their start, which the test below has.
        wait_for(lambda: registered_workers(database.url) == 2, 60, "the workers are not both running")
        load = [threading.Thread(target=upload, args=(i,)) for i in range(2)]
        for thread in load:
            thread.start()
        # Under load: uploads acknowledged and their inspections queued, when it stops.
        wait_for(lambda: len(acknowledged) >= 10, 60, "no uploads acknowledged")
        before = len(acknowledged)
        database.stop(stop_mode)
        assert wait_for(lambda: server.client().get("/readyz").status_code == 503, 10, "/readyz still ready")
        down = post_record(ingest, sid, json_body(600, seed=7), inspect="queue")
        assert down.status_code == 503 and "database" in down.json()["detail"], down.text
        # Down until the uploading clients have been answered 503 more than once: the load goes on.
        wait_for(lambda: answers[503] >= 2, 30, "no upload was answered 503 while it was down")
        database.start()
        wait_for(lambda: server.client().get("/readyz").status_code == 200, 30, "no recovery")
        during = len(acknowledged)
        wait_for(lambda: len(acknowledged) > during + 20, 30, "uploads did not resume")
        stop.set()
        for thread in load:
            thread.join(30)
        assert set(answers) <= {202, 503}, answers
        assert before > 0 and answers[503] > 0
        pending = set(acknowledged)

        def all_inspected() -> bool:
            return pending <= {v["record_id"] for v in verdicts(viewer, sid)}

        wait_for(all_inspected, 120, "acknowledged uploads without a verdict")
        inspected = [v["record_id"] for v in verdicts(viewer, sid) if v["record_id"] in pending]
        assert sorted(inspected) == sorted(pending), "a record got two verdicts"
    running = restarted.workers
    assert all(worker.alive() for worker in running), [w.output()[-3000:] for w in running]


def test_a_worker_started_while_postgresql_is_down_waits_for_it_and_then_runs(tmp_path: Path):
    """A worker started while its database is stopped (a host booting, a server restarting)
    waits for it instead of exiting, then works: like a running worker that loses the database."""
    with postgres.postgres_instance("late") as database:
        if database is None:
            pytest.skip(f"PostgreSQL unavailable: {postgres.missing_reason()}")
        upgrade_database(database.url)
        database.stop("fast")
        worker = Worker(database.url, tmp_path / "worker.log", **FAST_FAILOVER)
        try:
            wait_for(lambda: "cannot open the database" in worker.output(), 60, "the worker did not try")
            assert worker.alive(), worker.output()
            database.start()
            with psycopg.connect(conninfo(database.url), autocommit=True) as look:

                def working() -> bool:
                    return look.execute("SELECT count(*) FROM procrastinate_workers").fetchone() == (1,)

                wait_for(working, 60, "the worker never came up after the database did")
            assert worker.alive(), worker.output()
        finally:
            worker.stop()


def test_the_same_record_uploaded_at_once_is_stored_once(tenant):
    """Eight uploads of one record released together: one is created, the others get it back,
    and its queued inspections leave one verdict."""
    sid = create_structure(tenant.admin)["id"]
    train_fault_mode(tenant.admin, tenant.ingest, sid, "k2", seed=94)
    record = simulated("k2", 10.0, [95])
    body = npz_bytes(x=record.x, y=record.y, fs=record.fs)
    start = threading.Barrier(8)
    answers: list[httpx.Response] = []

    def upload() -> None:
        with http_client(
            base_url=str(tenant.ingest.base_url), headers=tenant.ingest.headers, timeout=60
        ) as client:
            start.wait()
            answers.append(post_record(client, sid, body, "application/x-npz", inspect="queue"))

    threads = [threading.Thread(target=upload) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60)
    # 202 while the record has no verdict from the active models; once its job has stored one, a
    # late duplicate gets that verdict back (200) instead of queueing the same work again.
    assert len(answers) == 8 and {a.status_code for a in answers} <= {200, 202}, [a.text for a in answers]
    assert all(a.json()["verdict"] is not None for a in answers if a.status_code == 200)
    assert len({a.json()["id"] for a in answers}) == 1, "one record, whoever won the race"
    assert sum(a.json()["created"] for a in answers) == 1
    record_id = answers[0].json()["id"]
    wait_for(lambda: verdicts_of(tenant.viewer, sid, record_id), 60, "no verdict")
    # Every job the uploads queued has ended: none is left to make a second verdict.
    wait_for(lambda: jobs_ended(tenant.admin), 60, "queued inspections still waiting")
    assert len(verdicts_of(tenant.viewer, sid, record_id)) == 1
