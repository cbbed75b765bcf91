"""The jobs' vocabulary: a job's states and what a backend offers, whichever backend runs them.

A leaf on purpose: the schemas, the routers and the metrics speak of jobs through it without
importing a backend, whose tasks import the domain (``service.jobs.backends`` picks the backend).
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal, Protocol

from sqlalchemy.orm import Session

from models.errors import InputError
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
