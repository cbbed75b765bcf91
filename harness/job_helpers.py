"""A monitored structure in a real database (SQLite file or PostgreSQL), built through the domain
code, with a job backend to queue and run its jobs: for the job and schedule tests that need to
decide exactly when a worker runs."""

from __future__ import annotations

import uuid
from dataclasses import dataclass
from pathlib import Path

import pytest
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from harness import migrated
from harness.api_helpers import TRAINING_K, simulated
from harness.live import LiveServer
from models.signals import checked_record, minimum_samples
from service.config import Settings
from service.db import make_engine, session_factory, transaction
from service.domain import modelling, records, structures
from service.jobs.backends import job_backend
from service.jobs.types import JobBackend
from service.schemas import Experiment, FaultModeTrain, StructureCreate
from service.security import Principal, Role
from service.tables import Organisation, Record, Structure
from simulator.theory import EXACT_TERMS

# SPEC §2's terms and one lagged 100 samples: records of 208 samples (the storage minimum) up to
# 100 + 5·lags + 8 = 308 (models.signals.minimum_samples) can be stored but not inspected with it.
EXACT_TERM_NAMES = [str(term) for term in EXACT_TERMS]
LONG_LAG_TERMS = [*EXACT_TERM_NAMES, "y[t-100]"]
TOO_SHORT = 250


def database_url(kind: str, tmp_path: Path, request: pytest.FixtureRequest) -> str:
    """A new database at the newest schema revision, holding nothing: a SQLite file, or a database
    on the session's PostgreSQL server."""
    if kind == "sqlite":
        return migrated.sqlite(tmp_path / "monitored.db")
    return migrated.postgresql(request.getfixturevalue("postgres_url"), f"jobs_{uuid.uuid4().hex[:12]}")


def run_jobs(server: LiveServer) -> None:
    """What `narxwatch worker --once` does for ``server``'s database: run every job due now, then
    return (for a server started without its embedded worker)."""
    engine = make_engine(server.settings.database_url)
    job_backend(server.settings, session_factory(engine), in_service=False).work(once=True)
    engine.dispose()


@dataclass
class Monitored:
    """An organisation's structure, with or without an active k2 model."""

    settings: Settings
    sessions: sessionmaker[Session]
    principal: Principal
    structure_id: int

    @classmethod
    def create(cls, url: str, terms: list[str] | None = None) -> Monitored:
        """One structure in the migrated database at ``url`` (``database_url``); with ``terms``,
        an active k2 model of those terms."""
        sessions = session_factory(make_engine(url))
        with transaction(sessions) as session:
            organisation = Organisation(name=f"org-{uuid.uuid4().hex[:8]}")
            session.add(organisation)
            session.flush()
            principal = Principal(organisation.id, Role.admin, key_id=0)
            structure = structures.create_structure(
                session, principal, StructureCreate(name="rig", fs=1500.0)
            )
        monitored = cls(Settings(database_url=url, embedded_worker=False), sessions, principal, structure.id)
        if terms is not None:
            monitored.train(terms, seed=1)
        return monitored

    def backend(self) -> JobBackend:
        return job_backend(self.settings, self.sessions, in_service=False)

    def store(self, fault: str, k: float, seed: object, n: int = 2000) -> int:
        """A simulated record stored as an upload with ``inspect=false`` stores it; its id."""
        record = simulated(fault, k, seed, n)
        with transaction(self.sessions) as session:
            structure = session.get(Structure, self.structure_id)
            x, y = checked_record(record.x, record.y, minimum_samples(self.settings.lags))
            stored, _ = records.store_record(session, structure, x, y, structure.fs, None)
            return stored.id

    def train(self, terms: list[str], seed: int) -> int:
        """A new active version of fault mode k2 with ``terms``; its id."""
        experiments = [
            Experiment(record_id=self.store("k2", k, [seed, i]), k=k) for i, k in enumerate(TRAINING_K)
        ]
        body = FaultModeTrain(name="k2", k_min=-32.0, k_max=32.0, experiments=experiments, terms=terms)
        with transaction(self.sessions) as session:
            version = modelling.train_fault_mode(
                session, self.principal, self.structure_id, body, self.settings
            )
            return version.id

    def record_ids(self) -> list[int]:
        with self.sessions() as session:
            query = select(Record.id).where(Record.structure_id == self.structure_id).order_by(Record.id)
            return list(session.scalars(query))
