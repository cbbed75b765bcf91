"""The distributed job backend: Procrastinate on PostgreSQL, run by ``narxwatch worker`` processes.

Any number of workers, on any machine that reaches the database. Procrastinate gives at-least-once
execution and retries with exponential backoff; its periodic tasks, deferred once per tick
however many workers run, sweep the schedules and hand back the jobs of workers that died (no
heartbeat for ``worker_stalled_seconds``). The service itself only defers jobs, in the
transaction of the request that asks for them.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import logging
import signal
import time
from typing import Any

import procrastinate
from procrastinate import JobContext, PsycopgConnector, RetryStrategy, SyncPsycopgConnector
from sqlalchemy import text
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from service.config import Settings
from service.domain import schedules
from service.jobs import QueueStats
from service.jobs.tasks import INSPECT_RECORD, REFINE, TASKS, TRAIN_MODEL

RETRY = RetryStrategy(max_attempts=5, exponential_wait=2)  # waits 2, 4, 8, 16 s between attempts
SWEEP_CRON = "* * * * * */2"  # croniter's sixth field is seconds: every 2 s
KEEP_SUCCEEDED_HOURS = 1
STATES = ("todo", "doing", "succeeded", "failed", "cancelled", "aborting", "aborted")
RESTART_FIRST, RESTART_MAX = 1.0, 30.0  # seconds between restarts of a worker that lost the database

log = logging.getLogger("narxwatch.jobs")

# Deferring needs no pool: jobs are written on the caller's own connection, in its transaction,
# by task name (this app declares no tasks). The workers' app declares them; ``work`` gives it a
# connector to the configured database.
deferrer = procrastinate.App(connector=SyncPsycopgConnector())
app = procrastinate.App(connector=PsycopgConnector())


def conninfo(database_url: str) -> str:
    """libpq's form of a SQLAlchemy ``postgresql+psycopg://`` URL."""
    return make_url(database_url).set(drivername="postgresql").render_as_string(hide_password=False)


def defer(session: Session, task: str, **args: Any) -> int:
    """Queue ``task(**args)`` in the session's transaction (committed with it); the job's id."""
    connection = session.connection().connection.driver_connection
    return deferrer.configure_task(task, connection=connection).defer(**args)


def _run(context: JobContext, task: str, **args: Any) -> None:
    sessions: sessionmaker[Session] = context.additional_context["sessions"]
    with sessions() as session:
        TASKS[task](session, context.additional_context["settings"], **args)


@app.task(name=INSPECT_RECORD, pass_context=True, retry=RETRY)
def inspect_record(context: JobContext, record_id: int) -> None:
    _run(context, INSPECT_RECORD, record_id=record_id)


@app.task(name=schedules.RUN_SCHEDULE, pass_context=True, retry=RETRY)
def run_schedule(context: JobContext, schedule_id: int, due_at: str) -> None:
    _run(context, schedules.RUN_SCHEDULE, schedule_id=schedule_id, due_at=due_at)


@app.task(name=TRAIN_MODEL, pass_context=True, retry=RETRY)
def train_model(context: JobContext, **args: Any) -> None:
    _run(context, TRAIN_MODEL, **args)


@app.task(name=REFINE, pass_context=True, retry=RETRY)
def refine(context: JobContext, **args: Any) -> None:
    _run(context, REFINE, **args)


@app.periodic(cron=SWEEP_CRON, periodic_id="sweep")
@app.task(name="sweep_schedules", pass_context=True, queueing_lock="sweep_schedules")
def sweep_schedules(context: JobContext, timestamp: int) -> None:
    sessions: sessionmaker[Session] = context.additional_context["sessions"]
    with sessions() as session:
        schedules.sweep(session, defer, dt.datetime.fromtimestamp(timestamp, dt.UTC))


@app.periodic(cron=SWEEP_CRON, periodic_id="stalled")
@app.task(name="retry_stalled_jobs", pass_context=True, queueing_lock="retry_stalled_jobs")
async def retry_stalled_jobs(context: JobContext, timestamp: int) -> None:
    """Jobs whose worker stopped sending heartbeats (killed, or cut off) run again."""
    settings: Settings = context.additional_context["settings"]
    manager = context.app.job_manager
    for job in await manager.get_stalled_jobs(seconds_since_heartbeat=settings.worker_stalled_seconds):
        await manager.retry_job(job)


@app.periodic(cron="*/10 * * * *", periodic_id="prune")
@app.task(name="prune_finished_jobs", pass_context=True, queueing_lock="prune_finished_jobs")
async def prune_finished_jobs(context: JobContext, timestamp: int) -> None:
    """Succeeded jobs (the sweeps every few seconds among them) are kept an hour, then dropped;
    verdicts are the lasting record. Failed jobs stay for an operator to look at."""
    await context.app.job_manager.delete_old_jobs(nb_hours=KEEP_SUCCEEDED_HOURS)


LATENCIES = text(
    "SELECT extract(epoch FROM done.at - deferred.at) FROM procrastinate_events done "
    "JOIN procrastinate_events deferred ON deferred.job_id = done.job_id AND deferred.type = 'deferred' "
    "WHERE done.type = 'succeeded' AND done.at >= now() - make_interval(secs => :window)"
)


def queue_stats(session: Session, window: dt.timedelta) -> QueueStats:
    """Jobs by Procrastinate status, and the defer-to-success latency of those that succeeded
    within ``window`` (from Procrastinate's event log)."""
    by_status = text("SELECT status::text, count(*) FROM procrastinate_jobs GROUP BY 1")
    depth = {**dict.fromkeys(STATES, 0), **dict(session.execute(by_status).all())}
    seconds = window.total_seconds()
    latencies = [float(v) for v in session.scalars(LATENCIES, {"window": seconds})]
    return QueueStats(depth=depth, latencies=latencies, window_seconds=seconds)


class DistributedBackend:
    """Procrastinate: this process defers; ``work`` runs a worker (``narxwatch worker``)."""

    name = "distributed"

    def __init__(self, sessions: sessionmaker[Session], settings: Settings) -> None:
        self._sessions = sessions
        self._settings = settings

    def defer(self, session: Session, task: str, **args: Any) -> int:
        return defer(session, task, **args)

    def queue_stats(self, session: Session, window: dt.timedelta) -> QueueStats:
        return queue_stats(session, window)

    def start(self) -> None:
        """Nothing runs in the service's process: the workers do."""

    def wake(self) -> None:
        """Workers hear of new jobs through PostgreSQL's LISTEN/NOTIFY."""

    def stop(self) -> None:
        """Nothing to stop in the service's process."""

    def work(self, once: bool, concurrency: int = 1) -> None:  # Procrastinate does not count
        """Run a Procrastinate worker until SIGINT/SIGTERM or, with ``once``, until the queue is
        empty. A worker that loses the database stops; it is started again, after a backoff,
        for as long as this process runs (its unfinished jobs go back to the queue as stalled)."""
        asyncio.run(self._supervise(once, concurrency))

    async def _supervise(self, once: bool, concurrency: int) -> None:
        stopping = asyncio.Event()
        loop = asyncio.get_running_loop()
        for signum in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(signum, stopping.set)
        delay = RESTART_FIRST
        while True:
            started = time.monotonic()
            worker = asyncio.create_task(self._run(once, concurrency))
            stop = asyncio.create_task(stopping.wait())
            await asyncio.wait({worker, stop}, return_when=asyncio.FIRST_COMPLETED)
            if stopping.is_set():
                worker.cancel()  # Procrastinate finishes the running jobs, then returns
                await asyncio.gather(worker, return_exceptions=True)
                return
            stop.cancel()
            error = worker.exception()
            if once and error is None:
                return
            if time.monotonic() - started > RESTART_MAX:
                delay = RESTART_FIRST
            log.warning(
                "the worker stopped (%s); starting it again in %.0f s", error or "lost the database", delay
            )
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stopping.wait(), delay)
            if stopping.is_set():
                return
            delay = min(2 * delay, RESTART_MAX)

    async def _run(self, once: bool, concurrency: int) -> None:
        connector = PsycopgConnector(conninfo=conninfo(self._settings.database_url))
        with app.replace_connector(connector) as worker:
            async with worker.open_async():
                await worker.run_worker_async(
                    wait=not once,
                    concurrency=concurrency,
                    additional_context={"sessions": self._sessions, "settings": self._settings},
                    update_heartbeat_interval=self._settings.worker_heartbeat_seconds,
                    stalled_worker_timeout=self._settings.worker_stalled_seconds,
                    install_signal_handlers=False,
                )
