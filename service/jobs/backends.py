"""Which job backend a process runs (``service.jobs``): the configured one, built on demand."""

from __future__ import annotations

from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

from service.config import Settings
from service.jobs.types import JobBackend


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
