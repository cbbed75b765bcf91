"""Inspections and schedules as jobs, on one of two backends behind one interface.

- ``embedded`` (the default on SQLite): jobs in the database's ``jobs`` table, run by a thread
  of each service process, which also sweeps the schedules. Nothing else to start.
- ``distributed`` (the default on PostgreSQL): Procrastinate, run by ``narxwatch worker``
  processes on any number of machines.

Either way a job is deferred in the transaction of the request that asks for it, so an
acknowledged upload always has its job; every job runs at least once, and its task is
idempotent, so a redelivered job changes nothing.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from service.config import Settings


@dataclass(frozen=True)
class QueueStats:
    """The queue at one moment: jobs by state, and how long recent ones took from enqueue to end."""

    depth: Mapping[str, int]
    latencies: Sequence[float]  # seconds, jobs finished within the last ``window_seconds``
    window_seconds: float


class JobBackend(Protocol):
    name: str

    def defer(self, session: Session, task: str, **args: Any) -> int:
        """Queue ``task(**args)`` in the session's transaction (committed with it); the job's id."""

    def queue_stats(self, session: Session, window: dt.timedelta) -> QueueStats: ...

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
