"""A structure's verdicts as columns over time, for its charts (k̂ with interval, Q per mode, k̂
against each operating condition, a healthy baseline's severity)."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from service.tables import RecordCondition, Verdict

# The charts hold the newest verdicts up to this many: beyond it a browser slows for no gain in
# what a person can see, and the verdict table pages through the rest.
MAX_CHART_VERDICTS = 20_000


@dataclass(frozen=True)
class TimelinePoint:
    verdict_id: int
    record_id: int
    acquired_at: dt.datetime
    status: str
    reference_mode: str | None
    k_hat: float | None
    interval_low: float | None
    interval_high: float | None
    modes: list[dict[str, Any]]
    novelty: dict[str, Any] | None  # the figures of a healthy baseline's judgement alone
    conditions: dict[str, float] = field(default_factory=dict)  # the record's, by name

    @property
    def severity(self) -> float | None:
        """A healthy baseline's severity (1 when healthy); None for the chain's verdicts and a free
        run that diverged."""
        return self.novelty.get("severity") if self.novelty is not None else None


@dataclass(frozen=True)
class Timeline:
    """The newest verdicts of a structure, oldest first; ``total`` counts all of them. ``units``
    names each condition some point with a k̂ was acquired under, with its unit (None: none given)."""

    points: list[TimelinePoint]
    total: int
    units: dict[str, str | None] = field(default_factory=dict)


def timeline(session: Session, structure_id: int, limit: int = MAX_CHART_VERDICTS) -> Timeline:
    """The structure's newest ``limit`` verdicts in acquisition order. Only the columns the charts
    draw are read: the model versions and counts of each verdict are left in the database."""
    columns = (
        Verdict.id,
        Verdict.record_id,
        Verdict.acquired_at,
        Verdict.status,
        Verdict.reference_mode,
        Verdict.k_hat,
        Verdict.interval_low,
        Verdict.interval_high,
        Verdict.modes,
        Verdict.novelty,
    )
    rows = session.execute(
        select(*columns)
        .where(Verdict.structure_id == structure_id)
        .order_by(Verdict.acquired_at.desc(), Verdict.id.desc())
        .limit(limit)
    ).all()
    total = session.scalar(select(func.count()).where(Verdict.structure_id == structure_id)) or 0
    # The conditions of those verdicts' records only: as bounded as the verdicts.
    of_records = (
        select(Verdict.record_id)
        .where(Verdict.structure_id == structure_id)
        .order_by(Verdict.acquired_at.desc(), Verdict.id.desc())
        .limit(limit)
    )
    conditions: dict[int, dict[str, float]] = {}
    units: dict[str, str | None] = {}
    with_k_hat = {row.record_id for row in rows if row.k_hat is not None}
    query = select(
        RecordCondition.record_id, RecordCondition.name, RecordCondition.value, RecordCondition.unit
    )
    for record_id, name, value, unit in session.execute(
        query.where(RecordCondition.structure_id == structure_id, RecordCondition.record_id.in_(of_records))
    ):
        conditions.setdefault(record_id, {})[name] = value
        if record_id in with_k_hat:
            units.setdefault(name, unit)
    points = [TimelinePoint(*row, conditions=conditions.get(row.record_id, {})) for row in reversed(rows)]
    return Timeline(points, total, dict(sorted(units.items())))
