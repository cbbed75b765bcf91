"""Inspections and schedules as jobs, on one of two backends behind one interface.

- ``embedded`` (the default on SQLite): jobs in the database's ``jobs`` table, run by a thread
  of each service process, which also sweeps the schedules. Nothing else to start.
- ``distributed`` (the default on PostgreSQL): Procrastinate, run by ``narxwatch worker``
  processes on any number of machines.

Either way a job is deferred in the transaction of the request that asks for it, so an
acknowledged upload always has its job; every job runs at least once, and its task is
idempotent, so a redelivered job changes nothing. A job that fails is retried with backoff,
unless its error says that running it again cannot succeed (``FINAL_ERRORS``): it then fails at
once, its reason stored for ``GET /jobs``. Every job belongs to an organisation, which alone
sees it.

Fair share: no organisation's backlog holds up another's jobs. A job is queued with priority
−n, n being its organisation's jobs waiting at that moment, and workers take the highest
priority first, then the oldest. Organisations' waiting jobs are thus taken in turn (the first of
each, then the second of each, …): a job queued behind a thousand of another organisation's
waits for one of them, not a thousand.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol

from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from models.errors import InputError
from service.config import Settings
from service.domain.errors import ConflictError, NotFoundError

# Errors of the input or of the state, not of the moment: a retry would fail the same way.
FINAL_ERRORS: tuple[type[Exception], ...] = (InputError, ConflictError, NotFoundError)

# One vocabulary for a job's state, whichever backend keeps it.
JobState = Literal["queued", "running", "done", "failed"]
JOB_STATES: tuple[JobState, ...] = ("queued", "running", "done", "failed")

# Seconds between a worker's attempts to reach a database that is away (starting, restarting).
RESTART_FIRST, RESTART_MAX = 1.0, 30.0


@dataclass(frozen=True)
class JobInfo:
    """A job as its organisation sees it: what it runs, how far it got, and why it failed."""

    id: int
    task: str
    args: Mapping[str, Any]
    state: JobState
    attempts: int
    error: str | None
    created_at: dt.datetime | None


def error_text(exc: BaseException) -> str:
    """How a job's failure is stored: the error's kind and its message."""
    return f"{type(exc).__name__}: {exc}"


@dataclass(frozen=True)
class QueueStats:
    """The queue at one moment: jobs by state, and how long recent ones took from enqueue to end."""

    depth: Mapping[str, int]
    latencies: Sequence[float]  # seconds, jobs finished within the last ``window_seconds``
    window_seconds: float


class JobBackend(Protocol):
    name: str

    def defer(self, session: Session, task: str, organisation_id: int, **args: Any) -> int:
        """Queue ``task(**args)`` for an organisation in the session's transaction (committed
        with it); the job's id, for ``GET /jobs/{id}``."""

    def queue_stats(self, session: Session, window: dt.timedelta) -> QueueStats: ...

    def list_jobs(
        self, session: Session, organisation_id: int, state: JobState | None, limit: int, before: int | None
    ) -> list[JobInfo]:
        """The organisation's jobs, newest first, optionally of one state, older than ``before``."""

    def get_job(self, session: Session, organisation_id: int, job_id: int) -> JobInfo | None:
        """One of the organisation's jobs; None if there is none with that id, or it is another's."""

    def start(self) -> None:
        """Start what runs inside a service process (the embedded worker), if anything."""

    def wake(self) -> None:
        """A job was just queued: look now rather than at the next poll."""

    def stop(self) -> None: ...

    def work(self, once: bool, concurrency: int = 1) -> int | None:
        """Run jobs in the calling thread (``narxwatch worker``): until stopped, or those due
        now; the number run, where the backend counts them."""


def backend_name(settings: Settings) -> str:
    """``settings.job_backend``, with ``auto`` resolved by the database: Procrastinate needs PostgreSQL."""
    if settings.job_backend != "auto":
        return settings.job_backend
    return "distributed" if make_url(settings.database_url).get_backend_name() == "postgresql" else "embedded"


def job_backend(settings: Settings, sessions: sessionmaker[Session], in_service: bool) -> JobBackend:
    """The configured backend; ``in_service``: for a service process (which runs the embedded
    worker unless ``embedded_worker`` is off) rather than for ``narxwatch worker``."""
    if backend_name(settings) == "distributed":
        if make_url(settings.database_url).get_backend_name() != "postgresql":
            raise ValueError("the distributed job backend (Procrastinate) needs a PostgreSQL database")
        from service.jobs.distributed import DistributedBackend

        return DistributedBackend(sessions, settings)
    from service.jobs.embedded import EmbeddedBackend

    return EmbeddedBackend(sessions, settings, run_in_process=in_service and settings.embedded_worker)
