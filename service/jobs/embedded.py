"""The embedded job backend: jobs queued in the database's ``jobs`` table, run by a thread.

Nothing else to start: each service process claims due jobs and runs them on a thread, which
also sweeps the schedules. ``narxwatch worker`` runs the same loop in a process of its own. A
claim is a lease (``locked_until``), renewed while the job runs, so a job whose worker died is
claimed again when the lease runs out, and only then: every job runs at least once, and running
it twice changes nothing. A failed job is retried with exponential backoff, up to
``MAX_ATTEMPTS``, unless its error is final (``FINAL_ERRORS``). The schedule sweep and the jobs
are kept apart: neither one's failure stops the other.
"""

from __future__ import annotations

import datetime as dt
import logging
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from sqlalchemy import and_, func, insert, or_, select, update
from sqlalchemy.orm import Session, sessionmaker

from service.config import Settings
from service.domain import notifications, renotify, retention, schedules
from service.jobs.tasks import TASKS
from service.jobs.types import FINAL_ERRORS, JOB_STATES, JobInfo, JobState, QueueStats, error_text
from service.tables import Job, JobCount, utcnow

MAX_ATTEMPTS = 5
LEASE = dt.timedelta(seconds=60)  # renewed every third of it while the job runs
FIRST_RETRY = dt.timedelta(seconds=1)  # then 2, 4, 8 … seconds
IDLE_POLL = 0.5  # seconds between looks at an empty queue
ENDED: tuple[JobState, ...] = ("done", "failed")  # the states counted in ``job_counts``

log = logging.getLogger("narxwatch.jobs")


def defer(session: Session, task: str, organisation_id: int, **args: Any) -> int:
    """Queue ``task(**args)`` for an organisation in the caller's transaction (committed with
    it), behind its organisation's waiting jobs (``service.jobs``: fair share); the job's id."""
    waiting = (
        select(func.count())
        .where(Job.organisation_id == organisation_id, Job.status == "queued")
        .scalar_subquery()
    )
    queued = insert(Job.__table__).values(
        organisation_id=organisation_id, task=task, args=args, priority=-waiting
    )
    return session.execute(queued.returning(Job.id)).scalar_one()


@dataclass(frozen=True)
class Claimed:
    id: int
    task: str
    args: dict[str, Any]
    attempts: int


def claim(session: Session, now: dt.datetime | None = None, lease: dt.timedelta = LEASE) -> Claimed | None:
    """Lease the due job (queued and due, or running with an expired lease) of the highest
    priority, the oldest of those (``service.jobs``: fair share); commits."""
    now = now or utcnow()
    due = or_(
        and_(Job.status == "queued", Job.run_after <= now),
        and_(Job.status == "running", Job.locked_until < now),
    )
    # A read first: an idle worker polls without taking the database's write lock.
    if session.scalar(select(Job.id).where(due).limit(1)) is None:
        session.rollback()
        return None
    first = select(Job.id).where(due).order_by(Job.priority.desc(), Job.id).limit(1).scalar_subquery()
    statement = (
        update(Job.__table__)
        .where(Job.id == first, due)  # re-checked: another worker may have leased it meanwhile
        .values(status="running", attempts=Job.attempts + 1, locked_until=now + lease)
        .returning(Job.id, Job.task, Job.args, Job.attempts)
    )
    row = session.execute(statement).one_or_none()
    session.commit()
    return Claimed(*row) if row is not None else None


def renew(session: Session, job: Claimed, lease: dt.timedelta = LEASE) -> bool:
    """Extend a running job's lease from now, if this claim of it still holds; commits."""
    still_ours = (Job.id == job.id, Job.status == "running", Job.attempts == job.attempts)
    renewed = session.execute(update(Job.__table__).where(*still_ours).values(locked_until=utcnow() + lease))
    session.commit()
    return renewed.rowcount == 1


def run(session: Session, job: Claimed, settings: Settings, now: dt.datetime | None = None) -> None:
    """Run a claimed job and record how it ended (a retry is due a backoff after ``now``); commits."""
    try:
        TASKS[job.task](session, settings, **job.args)
    except Exception as exc:  # any failure is the job's: retried, unless final
        session.rollback()
        _finish_failed(session, job, exc, now or utcnow())
        return
    _finish(session, job, status="done", finished_at=utcnow(), locked_until=None)


def _finish_failed(session: Session, job: Claimed, exc: Exception, now: dt.datetime) -> None:
    error = error_text(exc)
    if isinstance(exc, FINAL_ERRORS) or job.attempts >= MAX_ATTEMPTS:
        log.error("job %s failed for good after %s attempt(s): %s", job.id, job.attempts, error)
        _finish(session, job, status="failed", last_error=error, finished_at=utcnow(), locked_until=None)
        return
    delay = FIRST_RETRY * 2 ** (job.attempts - 1)
    log.warning("job %s failed (attempt %s), retried in %s: %s", job.id, job.attempts, delay, error)
    _finish(session, job, status="queued", last_error=error, run_after=now + delay, locked_until=None)


def _finish(session: Session, job: Claimed, status: JobState, **values: object) -> None:
    """Record how a claimed job ended, if the claim still holds; commits. A worker whose lease ran
    out, and whose job another worker claimed since, leaves the ending to that claim: each job
    ends once, so ``job_counts`` counts it once."""
    still_ours = (Job.id == job.id, Job.status == "running", Job.attempts == job.attempts)
    ended = session.execute(update(Job.__table__).where(*still_ours).values(status=status, **values))
    if ended.rowcount == 1 and status in ENDED:
        session.execute(update(JobCount).where(JobCount.state == status).values(count=JobCount.count + 1))
    session.commit()


def queue_stats(session: Session, window: dt.timedelta) -> QueueStats:
    """Jobs by status, and the enqueue-to-finish latency of those finished within ``window``.

    Queued and running jobs are counted in ``ix_jobs_due``, as many rows as the queue is deep;
    ended ones are read from ``job_counts``, which counts them as they end."""
    waiting = (
        select(Job.status, func.count()).where(Job.status.in_(("queued", "running"))).group_by(Job.status)
    )
    counts = [*session.execute(waiting), *session.execute(select(JobCount.state, JobCount.count))]
    depth = {**dict.fromkeys(JOB_STATES, 0), **dict(counts)}
    finished = select(Job.created_at, Job.finished_at).where(
        Job.status == "done", Job.finished_at >= utcnow() - window
    )
    latencies = [(end - start).total_seconds() for start, end in session.execute(finished)]
    return QueueStats(depth=depth, latencies=latencies, window_seconds=window.total_seconds())


def list_jobs(
    session: Session, organisation_id: int, state: JobState | None, limit: int, before: int | None
) -> list[JobInfo]:
    """The organisation's jobs, newest first, optionally of one state, older than ``before``."""
    query = select(Job).where(Job.organisation_id == organisation_id)
    if state is not None:
        query = query.where(Job.status == state)
    if before is not None:
        query = query.where(Job.id < before)
    return [_info(job) for job in session.scalars(query.order_by(Job.id.desc()).limit(limit))]


def get_job(session: Session, organisation_id: int, job_id: int) -> JobInfo | None:
    job = session.get(Job, job_id)
    return _info(job) if job is not None and job.organisation_id == organisation_id else None


def _info(job: Job) -> JobInfo:
    return JobInfo(
        id=job.id,
        task=job.task,
        args=job.args,
        state=job.status,  # type: ignore[arg-type]  # the column holds JOB_STATES only
        attempts=job.attempts,
        error=job.last_error,
        created_at=job.created_at,
    )


class EmbeddedBackend:
    """Jobs in the ``jobs`` table, run (with the schedule sweep) on a thread of this process.

    ``run_in_process`` False leaves the running to ``narxwatch worker`` processes: the service
    then only queues.
    """

    name = "embedded"

    def __init__(
        self,
        sessions: sessionmaker[Session],
        settings: Settings,
        run_in_process: bool,
        lease: dt.timedelta = LEASE,
    ) -> None:
        self._sessions = sessions
        self._settings = settings
        self._lease = lease
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = (
            threading.Thread(target=self._loop, name="narxwatch-jobs", daemon=True)
            if run_in_process
            else None
        )

    # The queue's operations are this module's functions over the caller's session.
    defer = staticmethod(defer)
    queue_stats = staticmethod(queue_stats)
    list_jobs = staticmethod(list_jobs)
    get_job = staticmethod(get_job)

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
        """Run jobs in this thread: those due now (``once``; an error of the queue then ends the
        call), or until stopped; the number run. One at a time: SQLite has one writer, and more
        workers are more processes."""
        if once:
            self._sweep_all()
            return self.run_due()
        count = 0
        while not self._stop.is_set():
            self._sweep_all()
            count += self._guarded(self.run_due, "run the jobs")
            self._wake.wait(IDLE_POLL)
            self._wake.clear()
        return count

    def _sweep_all(self) -> None:
        self._guarded(self.sweep, "sweep the schedules")
        self._guarded(self.sweep_notifications, "sweep the notifications")
        self._guarded(self.sweep_retention, "sweep the retention")

    @staticmethod
    def _guarded(step: Callable[[], int], what: str) -> int:
        """Run one step of the loop; a failure (the database away for a while) is logged and
        leaves the other step, and the next round, to go on."""
        try:
            return step()
        except Exception:
            log.exception("the job worker could not %s; retrying", what)
            return 0

    def sweep(self) -> int:
        """Queue a job for each schedule due now; the number queued."""
        with self._sessions() as session:
            deferred = schedules.sweep(session, defer)
            session.commit()
            return deferred

    def sweep_notifications(self) -> int:
        """Announce again the open alarms due for it, then queue a job for each notification
        delivery due now; the number queued."""
        with self._sessions() as session:
            renotify.sweep(session, dt.timedelta(seconds=self._settings.renotify_after_seconds))
            return notifications.sweep(session, defer)

    def sweep_retention(self) -> int:
        """Queue a pruning for each organisation due one; the number queued."""
        with self._sessions() as session:
            every = dt.timedelta(seconds=self._settings.retention_every_seconds)
            return retention.sweep(session, defer, every)

    def run_due(self) -> int:
        """Run every job due now; the number run."""
        count = 0
        while not self._stop.is_set():
            with self._sessions() as session:
                job = claim(session, lease=self._lease)
                if job is None:
                    return count
                with self._renewing(job):
                    run(session, job, self._settings)
            count += 1
        return count

    @contextmanager
    def _renewing(self, job: Claimed) -> Iterator[None]:
        """Renew the job's lease every third of it while it runs (a heartbeat), so that a job
        running longer than one lease is not claimed by a second worker."""
        done = threading.Event()

        def beat() -> None:
            while not done.wait(self._lease.total_seconds() / 3):
                try:
                    with self._sessions() as session:
                        renew(session, job, self._lease)
                except Exception:  # the database away for a moment: the next beat tries again
                    log.exception("could not renew the lease of job %s", job.id)

        heart = threading.Thread(target=beat, name=f"narxwatch-lease-{job.id}", daemon=True)
        heart.start()
        try:
            yield
        finally:
            done.set()
            heart.join()

    def _loop(self) -> None:
        self.work(once=False)
