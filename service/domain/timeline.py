"""A structure's verdicts as columns over time, for its charts (k̂ with interval, Q per mode)."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from service.tables import Verdict

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


@dataclass(frozen=True)
class Timeline:
    """The newest verdicts of a structure, oldest first; ``total`` counts all of them."""

    points: list[TimelinePoint]
    total: int


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
    )
    rows = session.execute(
        select(*columns)
        .where(Verdict.structure_id == structure_id)
        .order_by(Verdict.acquired_at.desc(), Verdict.id.desc())
        .limit(limit)
    ).all()
    total = session.scalar(select(func.count()).where(Verdict.structure_id == structure_id)) or 0
    return Timeline([TimelinePoint(*row) for row in reversed(rows)], total)
