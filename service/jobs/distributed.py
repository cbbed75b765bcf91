"""The distributed job backend: Procrastinate on PostgreSQL, run by ``narxwatch worker`` processes.

Any number of workers, on any machine that reaches the database. Procrastinate gives at-least-once
execution and retries with exponential backoff (not for ``FINAL_ERRORS``, which fail at once;
the last error of a job is kept in ``job_errors``); its periodic tasks, deferred once per tick
however many workers run, sweep the schedules and the notifications and hand back the jobs of
workers that died (no heartbeat for ``worker_stalled_seconds``) every ``worker_sweep_seconds``.
The service itself only defers jobs, in the transaction of the request that asks for them.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import json
import logging
import signal
import time
from typing import Any

import procrastinate
from procrastinate import JobContext, PsycopgConnector, RetryStrategy, SyncPsycopgConnector
from procrastinate.jobs import Job as ProcrastinateJob
from procrastinate.periodic import PeriodicRegistry
from procrastinate.retry import RetryDecision
from sqlalchemy import text
from sqlalchemy.dialects.postgresql import insert
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from service.config import Settings
from service.domain import notifications, renotify, retention, schedules
from service.jobs.tasks import TASKS
from service.jobs.types import (
    FINAL_ERRORS,
    RESTART_FIRST,
    RESTART_MAX,
    JobInfo,
    JobState,
    QueueStats,
    error_text,
)
from service.tables import JobError, utcnow


class RetryUnlessFinal(RetryStrategy):
    """Procrastinate's backoff for errors of the moment; none for ``FINAL_ERRORS``, which a
    retry cannot mend (Procrastinate's own ``retry_exceptions`` lists what to retry, not what not to)."""

    def get_retry_decision(self, *, exception: BaseException, job: ProcrastinateJob) -> RetryDecision | None:
        if isinstance(exception, FINAL_ERRORS):
            return None
        return super().get_retry_decision(exception=exception, job=job)


RETRY = RetryUnlessFinal(max_attempts=5, exponential_wait=2)  # waits 2, 4, 8, 16 s between attempts
KEEP_SUCCEEDED_HOURS = 1
STATES = ("todo", "doing", "succeeded", "failed", "cancelled", "aborting", "aborted")
# Procrastinate's states in the service's vocabulary (narxwatch cancels and aborts nothing).
AS_JOB_STATE: dict[str, JobState] = {
    "todo": "queued",
    "doing": "running",
    "aborting": "running",
    "succeeded": "done",
    "failed": "failed",
    "cancelled": "failed",
    "aborted": "failed",
}

log = logging.getLogger("narxwatch.jobs")

# Deferring needs no pool: jobs are written on the caller's own connection, in its transaction,
# by task name (this app declares no tasks). The workers' app declares them; ``work`` gives it a
# connector to the configured database.
deferrer = procrastinate.App(connector=SyncPsycopgConnector())
app = procrastinate.App(connector=PsycopgConnector())


def conninfo(database_url: str) -> str:
    """libpq's form of a SQLAlchemy ``postgresql+psycopg://`` URL."""
    return make_url(database_url).set(drivername="postgresql").render_as_string(hide_password=False)


# An organisation's jobs waiting to run, which a job it defers is queued behind (fair share).
WAITING = text(
    "SELECT count(*) FROM procrastinate_jobs WHERE status = 'todo' AND args @> CAST(:owner AS jsonb)"
)


def defer(session: Session, task: str, organisation_id: int, **args: Any) -> int:
    """Queue ``task(**args)`` for an organisation in the session's transaction (committed with
    it), behind its organisation's waiting jobs (``service.jobs``: fair share; Procrastinate's
    workers take the highest priority first, then the oldest); the job's id. The organisation
    travels in the job's arguments, where ``GET /jobs`` looks for it."""
    waiting = session.execute(WAITING, {"owner": _owner(organisation_id)}).scalar_one()
    connection = session.connection().connection.driver_connection
    deferrer_of_task = deferrer.configure_task(task, connection=connection, priority=-waiting)
    return deferrer_of_task.defer(organisation_id=organisation_id, **args)


def _run(context: JobContext, task: str, **args: Any) -> None:
    sessions: sessionmaker[Session] = context.additional_context["sessions"]
    try:
        with sessions() as session:
            TASKS[task](session, context.additional_context["settings"], **args)
            session.commit()
    except Exception as exc:
        assert context.job is not None and context.job.id is not None  # a running job has both
        _keep_error(sessions, context.job.id, error_text(exc))
        raise


def _keep_error(sessions: sessionmaker[Session], job_id: int, error: str) -> None:
    """Store a job's last error, which Procrastinate does not; on a connection of its own, as
    the job's may be the reason it failed. Not storing it (the database away) must not change
    how the job ends, so that failure is only logged."""
    values = {"job_id": job_id, "error": error, "at": utcnow()}
    upsert = insert(JobError.__table__).values(values)
    upsert = upsert.on_conflict_do_update(
        index_elements=["job_id"], set_={"error": error, "at": values["at"]}
    )
    try:
        with sessions() as session:
            session.execute(upsert)
            session.commit()
    except Exception:
        log.exception("the error of job %s could not be stored: %s", job_id, error)


def _declare(task: str) -> None:
    """Declare a task of ``TASKS`` to Procrastinate. The organisation a job was deferred for is
    in its arguments for ``GET /jobs``, not for the task (None in jobs deferred before jobs knew
    their organisation)."""

    def run(context: JobContext, organisation_id: int | None = None, **args: Any) -> None:
        _run(context, task, **args)

    app.task(name=task, pass_context=True, retry=RETRY)(run)


for _task in TASKS:  # every task of the service, whichever backend runs it
    _declare(_task)


@app.task(name="sweep_schedules", pass_context=True, queueing_lock="sweep_schedules")
def sweep_schedules(context: JobContext, timestamp: int) -> None:
    sessions: sessionmaker[Session] = context.additional_context["sessions"]
    with sessions() as session:
        schedules.sweep(session, defer, dt.datetime.fromtimestamp(timestamp, dt.UTC))
        session.commit()


@app.task(name="sweep_notifications", pass_context=True, queueing_lock="sweep_notifications")
def sweep_notifications(context: JobContext, timestamp: int) -> None:
    """Announce again the open alarms due for it (``service.domain.renotify``), then defer a job
    for each notification delivery due (``service.domain.notifications``)."""
    sessions: sessionmaker[Session] = context.additional_context["sessions"]
    settings: Settings = context.additional_context["settings"]
    with sessions() as session:
        renotify.sweep(session, dt.timedelta(seconds=settings.renotify_after_seconds))
        notifications.sweep(session, defer)


@app.task(name="sweep_retention", pass_context=True, queueing_lock="sweep_retention")
def sweep_retention(context: JobContext, timestamp: int) -> None:
    """Defer a pruning for each organisation due one (``service.domain.retention``): every
    minute is often enough for a period of hours."""
    sessions: sessionmaker[Session] = context.additional_context["sessions"]
    settings: Settings = context.additional_context["settings"]
    with sessions() as session:
        every = dt.timedelta(seconds=settings.retention_every_seconds)
        retention.sweep(session, defer, every, dt.datetime.fromtimestamp(timestamp, dt.UTC))


@app.task(name="retry_stalled_jobs", pass_context=True, queueing_lock="retry_stalled_jobs")
async def retry_stalled_jobs(context: JobContext, timestamp: int) -> None:
    """Jobs whose worker stopped sending heartbeats (killed, or cut off) run again."""
    settings: Settings = context.additional_context["settings"]
    manager = context.app.job_manager
    for job in await manager.get_stalled_jobs(seconds_since_heartbeat=settings.worker_stalled_seconds):
        await manager.retry_job(job)


@app.task(name="prune_finished_jobs", pass_context=True, queueing_lock="prune_finished_jobs")
async def prune_finished_jobs(context: JobContext, timestamp: int) -> None:
    """Succeeded jobs (the sweeps every few seconds among them) are kept an hour, then dropped;
    verdicts are the lasting record. Failed jobs stay for an operator to look at. The errors
    kept for jobs now gone go with them."""
    await context.app.job_manager.delete_old_jobs(nb_hours=KEEP_SUCCEEDED_HOURS)
    await context.app.connector.execute_query_async(
        "DELETE FROM job_errors e WHERE NOT EXISTS (SELECT FROM procrastinate_jobs j WHERE j.id = e.job_id)"
    )


def schedule_periodic(sweep_seconds: int) -> None:
    """Register the periodic tasks with Procrastinate, the sweeps every ``sweep_seconds`` (the
    ``worker_sweep_seconds`` setting). As a worker starts, not at import as ``app.periodic``'s
    decorator would: the worker reads the registry when it starts its periodic deferrer, so the
    period can be the settings' of the process. A new registry, as Procrastinate refuses a
    task registered twice."""
    app.periodic_registry = PeriodicRegistry()
    sweep = f"* * * * * */{sweep_seconds}"  # croniter's sixth field is seconds
    for task, cron, periodic_id in (
        (sweep_schedules, sweep, "sweep"),
        (sweep_notifications, sweep, "notifications"),
        (retry_stalled_jobs, sweep, "stalled"),
        (sweep_retention, "* * * * *", "retention"),
        (prune_finished_jobs, "*/10 * * * *", "prune"),
    ):
        app.periodic(cron=cron, periodic_id=periodic_id)(task)


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


JOBS = """
SELECT j.id, j.task_name, j.args, j.status::text, j.attempts, e.error,
       (SELECT min(d.at) FROM procrastinate_events d WHERE d.job_id = j.id AND d.type = 'deferred')
FROM procrastinate_jobs j LEFT JOIN job_errors e ON e.job_id = j.id
WHERE j.args @> CAST(:owner AS jsonb)"""


def list_jobs(
    session: Session, organisation_id: int, state: JobState | None, limit: int, before: int | None
) -> list[JobInfo]:
    """The organisation's jobs, newest first, optionally of one state (in the service's words),
    older than ``before``."""
    statuses = [status for status, ours in AS_JOB_STATE.items() if state in (None, ours)]
    query = text(
        f"{JOBS} AND j.status::text = ANY(:statuses) AND j.id < :before ORDER BY j.id DESC LIMIT :limit"
    )
    params = {
        "owner": _owner(organisation_id),
        "statuses": statuses,
        "limit": limit,
        "before": before or 2**63 - 1,
    }
    return [_info(*row) for row in session.execute(query, params)]


def get_job(session: Session, organisation_id: int, job_id: int) -> JobInfo | None:
    row = session.execute(text(f"{JOBS} AND j.id = :id"), {"owner": _owner(organisation_id), "id": job_id})
    found = row.one_or_none()
    return _info(*found) if found is not None else None


def _owner(organisation_id: int) -> str:
    return json.dumps({"organisation_id": organisation_id})


def _info(
    job_id: int,
    task: str,
    args: dict[str, Any],
    status: str,
    attempts: int,
    error: str | None,
    created_at: dt.datetime | None,
) -> JobInfo:
    task_args = {name: value for name, value in args.items() if name != "organisation_id"}
    return JobInfo(job_id, task, task_args, AS_JOB_STATE[status], attempts, error, created_at)


class DistributedBackend:
    """Procrastinate: this process defers; ``work`` runs a worker (``narxwatch worker``)."""

    name = "distributed"

    def __init__(self, sessions: sessionmaker[Session], settings: Settings) -> None:
        self._sessions = sessions
        self._settings = settings

    # The queue's operations are this module's functions over the caller's session.
    defer = staticmethod(defer)
    queue_stats = staticmethod(queue_stats)
    list_jobs = staticmethod(list_jobs)
    get_job = staticmethod(get_job)

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
        schedule_periodic(self._settings.worker_sweep_seconds)
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
