"""The embedded job backend: inspections queued in the database and run by an in-process worker.

Nothing else to start: the service's own process claims due jobs from the ``jobs`` table and
runs them on a thread. A claim is a lease (``locked_until``), so a job whose worker died is
claimed again when the lease runs out: every job runs at least once, and running it twice
changes nothing (one verdict per record and model set). A failed job is retried with
exponential backoff, up to ``MAX_ATTEMPTS``.
"""

from __future__ import annotations

import datetime as dt
import logging
import threading
from dataclasses import dataclass

from sqlalchemy import and_, insert, or_, select, update
from sqlalchemy.orm import Session, sessionmaker

from service.config import Settings
from service.db import writing
from service.domain.inspections import inspect_record
from service.tables import Job, Record, Structure, utcnow

INSPECT = "inspect_record"
MAX_ATTEMPTS = 5
LEASE = dt.timedelta(seconds=60)  # longer than any inspection takes
FIRST_RETRY = dt.timedelta(seconds=1)  # then 2, 4, 8 … seconds
IDLE_POLL = 0.5  # seconds between looks at an empty queue

log = logging.getLogger("narxwatch.jobs")


def enqueue_inspection(session: Session, record_id: int) -> None:
    """Queue an inspection of a record, in the caller's transaction (committed with it)."""
    session.execute(insert(Job.__table__), {"task": INSPECT, "record_id": record_id})


@dataclass(frozen=True)
class Claimed:
    id: int
    record_id: int
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
        .returning(Job.id, Job.record_id, Job.attempts)
    )
    with writing(session):
        row = session.execute(statement).one_or_none()
        session.commit()
    return Claimed(*row) if row is not None else None


def run(session: Session, job: Claimed, settings: Settings, now: dt.datetime | None = None) -> None:
    """Run a claimed job and record how it ended (a retry is due a backoff after ``now``); commits."""
    try:
        record = session.get(Record, job.record_id)
        if record is None:  # deleted meanwhile (records cascade to their jobs)
            raise LookupError(f"record {job.record_id} no longer exists")
        structure = session.get(Structure, record.structure_id)
        assert structure is not None  # a record's structure is a foreign key
        inspect_record(session, record, structure, settings)
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


class EmbeddedWorker:
    """A thread that runs due jobs until stopped; ``wake`` shortens the wait after an enqueue."""

    def __init__(self, sessions: sessionmaker[Session], settings: Settings) -> None:
        self._sessions = sessions
        self._settings = settings
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="narxwatch-jobs", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def wake(self) -> None:
        self._wake.set()

    def alive(self) -> bool:
        return self._thread.is_alive()

    def join(self, timeout: float) -> None:
        self._thread.join(timeout)

    def stop(self, timeout: float = 10.0) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout)

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
        while not self._stop.is_set():
            try:
                self.run_due()
            except Exception:  # the database may be away for a while: keep the worker alive
                log.exception("the job worker could not reach the queue; retrying")
            self._wake.wait(IDLE_POLL)
            self._wake.clear()
