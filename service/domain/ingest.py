"""Ingesting a record: stored once by content, inspected on request, written under the writer gate."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from dataclasses import dataclass

from numpy.typing import ArrayLike
from sqlalchemy.orm import Session

from service.config import Settings
from service.db import writing
from service.domain import inspections, records, structures
from service.security import Principal
from service.tables import Record, Verdict

QueueInspection = Callable[[Session, int], None]  # queue(session, record_id), in its transaction


@dataclass(frozen=True)
class Ingested:
    record: Record
    created: bool  # False when the same data had been stored before
    verdict: Verdict | None


def ingest_record(
    session: Session,
    principal: Principal,
    settings: Settings,
    structure_id: int,
    x: ArrayLike,
    y: ArrayLike,
    fs: float | None,
    acquired_at: dt.datetime | None,
    inspect: bool,
    queue: QueueInspection | None = None,
) -> Ingested:
    """Store a record and, with ``inspect``, its verdict under the active fault-mode models, or
    through ``queue`` an inspection job in the same transaction; commits.

    The verdict is computed before the first write, so that the write lock (SQLite's, or the
    writer gate in front of it) is held only for the inserts and their commit.
    """
    structure = structures.get_structure(session, principal, structure_id)
    evaluation = inspections.evaluate(session, structure, settings, x, y) if inspect else None
    if queue is not None:
        inspections.models_to_inspect_with(session, structure)  # refused now, not failed later
    with writing(session):
        record, created = records.store_record(
            session, structure, x, y, fs, acquired_at, records.minimum_samples(settings.lags)
        )
        verdict = (
            inspections.store_verdict(session, record, structure, evaluation, created) if evaluation else None
        )
        if queue is not None and (created or not inspections.has_verdict(session, record.id)):
            queue(session, record.id)
        session.commit()
    return Ingested(record, created, verdict)
