"""The embedded job backend: jobs queued in the database's ``jobs`` table, run by a thread.

Nothing else to start: each service process claims due jobs and runs them on a thread, which
also sweeps the schedules. ``narxwatch worker`` runs the same loop in a process of its own. A
claim is a lease (``locked_until``), so a job whose worker died is claimed again when the lease
runs out: every job runs at least once, and running it twice changes nothing. A failed job is
retried with exponential backoff, up to ``MAX_ATTEMPTS``.
"""

from __future__ import annotations

import datetime as dt
import logging
import threading
from dataclasses import dataclass
from typing import Any

from sqlalchemy import and_, func, insert, or_, select, update
from sqlalchemy.orm import Session, sessionmaker

from service.config import Settings
from service.db import writing
from service.domain import schedules
from service.jobs import QueueStats
from service.jobs.tasks import TASKS
from service.tables import Job, utcnow

STATES = ("queued", "running", "done", "failed")
MAX_ATTEMPTS = 5
LEASE = dt.timedelta(seconds=60)  # longer than any inspection takes
FIRST_RETRY = dt.timedelta(seconds=1)  # then 2, 4, 8 … seconds
IDLE_POLL = 0.5  # seconds between looks at an empty queue

log = logging.getLogger("narxwatch.jobs")


def defer(session: Session, task: str, **args: Any) -> int:
    """Queue ``task(**args)`` in the caller's transaction (committed with it); the job's id."""
    return session.execute(insert(Job.__table__).returning(Job.id), {"task": task, "args": args}).scalar_one()


@dataclass(frozen=True)
class Claimed:
    id: int
    task: str
    args: dict[str, Any]
    attempts: int


def claim(session: Session, now: dt.datetime | None = None) -> Claimed | None:
    """Lease the oldest due job (queued and due, or running with an expired lease); commits."""
    now = now or utcnow()
    due = or_(
        and_(Job.status == "queued", Job.run_after <= now),
        and_(Job.status == "running", Job.locked_until < now),
    )
    # A read first: an idle worker polls without taking the database's write lock.
    if session.scalar(select(Job.id).where(due).limit(1)) is None:
        session.rollback()
        return None
    oldest = select(Job.id).where(due).order_by(Job.id).limit(1).scalar_subquery()
    statement = (
        update(Job.__table__)
        .where(Job.id == oldest, due)  # re-checked: another worker may have leased it meanwhile
        .values(status="running", attempts=Job.attempts + 1, locked_until=now + LEASE)
        .returning(Job.id, Job.task, Job.args, Job.attempts)
    )
    with writing(session):
        row = session.execute(statement).one_or_none()
        session.commit()
    return Claimed(*row) if row is not None else None


def run(session: Session, job: Claimed, settings: Settings, now: dt.datetime | None = None) -> None:
    """Run a claimed job and record how it ended (a retry is due a backoff after ``now``); commits."""
    try:
        TASKS[job.task](session, settings, **job.args)
    except Exception as exc:  # any failure is the job's, and is retried
        session.rollback()
        _finish_failed(session, job, f"{type(exc).__name__}: {exc}", now or utcnow())
        return
    _finish(session, job.id, status="done", finished_at=utcnow(), locked_until=None)


def _finish_failed(session: Session, job: Claimed, error: str, now: dt.datetime) -> None:
    if job.attempts >= MAX_ATTEMPTS:
        log.error("job %s failed for good after %s attempts: %s", job.id, job.attempts, error)
        _finish(session, job.id, status="failed", last_error=error, finished_at=utcnow(), locked_until=None)
        return
    delay = FIRST_RETRY * 2 ** (job.attempts - 1)
    log.warning("job %s failed (attempt %s), retried in %s: %s", job.id, job.attempts, delay, error)
    _finish(session, job.id, status="queued", last_error=error, run_after=now + delay, locked_until=None)


def _finish(session: Session, job_id: int, **values: object) -> None:
    with writing(session):
        session.execute(update(Job.__table__).where(Job.id == job_id).values(**values))
        session.commit()


def queue_stats(session: Session, window: dt.timedelta) -> QueueStats:
    """Jobs by status, and the enqueue-to-finish latency of those finished within ``window``."""
    counts = session.execute(select(Job.status, func.count()).group_by(Job.status)).all()
    depth = {**dict.fromkeys(STATES, 0), **dict(counts)}
    finished = select(Job.created_at, Job.finished_at).where(
        Job.status == "done", Job.finished_at >= utcnow() - window
    )
    latencies = [(end - start).total_seconds() for start, end in session.execute(finished)]
    return QueueStats(depth=depth, latencies=latencies, window_seconds=window.total_seconds())


class EmbeddedBackend:
    """Jobs in the ``jobs`` table, run (with the schedule sweep) on a thread of this process.

    ``run_in_process`` False leaves the running to ``narxwatch worker`` processes: the service
    then only queues.
    """

    name = "embedded"

    def __init__(self, sessions: sessionmaker[Session], settings: Settings, run_in_process: bool) -> None:
        self._sessions = sessions
        self._settings = settings
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = (
            threading.Thread(target=self._loop, name="narxwatch-jobs", daemon=True)
            if run_in_process
            else None
        )

    def defer(self, session: Session, task: str, **args: Any) -> int:
        return defer(session, task, **args)

    def queue_stats(self, session: Session, window: dt.timedelta) -> QueueStats:
        return queue_stats(session, window)

    def start(self) -> None:
        if self._thread is not None:
            self._thread.start()

    def wake(self) -> None:
        self._wake.set()

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None and self._thread.is_alive():
            self._thread.join(timeout)

    def work(self, once: bool, concurrency: int = 1) -> int:
        """Run jobs in this thread: those due now (``once``), or until stopped; the number run.
        One at a time: SQLite has one writer, and more workers are more processes."""
        if once:
            self.sweep()
            return self.run_due()
        count = 0
        while not self._stop.is_set():
            try:
                self.sweep()
                count += self.run_due()
            except Exception:  # the database may be away for a while: keep the worker alive
                log.exception("the job worker could not reach the queue; retrying")
            self._wake.wait(IDLE_POLL)
            self._wake.clear()
        return count

    def sweep(self) -> int:
        """Queue a job for each schedule due now; the number queued."""
        with self._sessions() as session:
            return schedules.sweep(session, defer)

    def run_due(self) -> int:
        """Run every job due now; the number run."""
        count = 0
        while not self._stop.is_set():
            with self._sessions() as session:
                job = claim(session)
                if job is None:
                    return count
                run(session, job, self._settings)
            count += 1
        return count

    def _loop(self) -> None:
        self.work(once=False)
