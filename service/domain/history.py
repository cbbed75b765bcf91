"""The fault history of a structure: filtered, cursor-paginated, newest first; and its summary."""

from __future__ import annotations

import base64
import binascii
import datetime as dt
from dataclasses import dataclass

import numpy as np
from sqlalchemy import and_, or_, select
from sqlalchemy.orm import Session

from models.errors import InputError
from models.inspection import Status
from service.domain import fleet
from service.domain.inspections import CONDITIONS, MODEL_REFS
from service.domain.paging import Page
from service.domain.structures import get_structure
from service.schemas import MAX_ID
from service.security import Principal
from service.tables import Verdict

TREND_POINTS = 100
SECONDS_PER_DAY = 86_400.0


@dataclass(frozen=True)
class HistorySummary:
    """Where a structure stands: its counts by status, its latest verdict, the newest verdicts
    oldest first (``trend``) and the slope of their k̂ [%/day]."""

    structure_id: int
    total: int
    counts: dict[str, int]
    latest: Verdict | None
    trend: list[Verdict]
    k_hat_slope_per_day: float | None


def history(
    session: Session,
    principal: Principal,
    structure_id: int,
    *,
    start: dt.datetime | None,
    end: dt.datetime | None,
    status: Status | None,
    fault_mode: str | None,
    cursor: str | None,
    limit: int,
) -> Page[Verdict, str]:
    """Verdicts of a structure acquired in [start, end), newest first, ``limit`` at a time."""
    get_structure(session, principal, structure_id)
    query = select(Verdict).where(Verdict.structure_id == structure_id)
    if start is not None:
        query = query.where(Verdict.acquired_at >= start)
    if end is not None:
        query = query.where(Verdict.acquired_at < end)
    if status is not None:
        query = query.where(Verdict.status == status)
    if fault_mode is not None:
        query = query.where(Verdict.fault_mode == fault_mode)
    if cursor is not None:
        at, verdict_id = _decode(cursor)
        query = query.where(
            or_(Verdict.acquired_at < at, and_(Verdict.acquired_at == at, Verdict.id < verdict_id))
        )
    query = query.order_by(Verdict.acquired_at.desc(), Verdict.id.desc()).limit(limit + 1)
    rows = list(session.scalars(query.options(MODEL_REFS, CONDITIONS)))
    page, more = rows[:limit], len(rows) > limit
    return Page(
        items=page,
        next_cursor=_encode(page[-1].acquired_at, page[-1].id) if more else None,
    )


def summary(session: Session, principal: Principal, structure_id: int) -> HistorySummary:
    """Counts by status (kept on write, in the structure's state), the latest verdict and the trend.

    The latest is the state's, and the trend ends with it: a verdict acquired after it was in
    the future when stored (``fleet.count_verdict``), and is no part of where the structure stands.
    """
    structure = get_structure(session, principal, structure_id)
    status = fleet.structure_status(session, structure)
    latest = status.latest
    newest = (
        list(
            session.scalars(
                select(Verdict)
                .where(Verdict.structure_id == structure_id, Verdict.acquired_at <= latest.acquired_at)
                .order_by(Verdict.acquired_at.desc(), Verdict.id.desc())
                .limit(TREND_POINTS)
                .options(MODEL_REFS, CONDITIONS)
            )
        )
        if latest is not None
        else []
    )
    counts = status.counts
    return HistorySummary(
        structure_id=structure_id,
        total=sum(counts.values()),
        counts=counts,
        latest=newest[0] if newest else None,
        trend=newest[::-1],
        k_hat_slope_per_day=_slope(newest),
    )


def _slope(newest: list[Verdict]) -> float | None:
    """k̂ per day over the newest verdicts of the latest verdict's reference mode."""
    if not newest or newest[0].reference_mode is None:
        return None
    mode = newest[0].reference_mode
    points = [
        (v.acquired_at.timestamp(), v.k_hat)
        for v in newest
        if v.reference_mode == mode and v.k_hat is not None
    ]
    times = np.array([t for t, _ in points])
    if len(points) < 2 or np.ptp(times) == 0:
        return None
    slope = np.polyfit(times / SECONDS_PER_DAY, [k for _, k in points], 1)[0]
    return float(slope)


def _encode(at: dt.datetime, verdict_id: int) -> str:
    return base64.urlsafe_b64encode(f"{at.isoformat()}|{verdict_id}".encode()).decode()


def _decode(cursor: str) -> tuple[dt.datetime, int]:
    try:
        at, verdict_id = base64.urlsafe_b64decode(cursor.encode()).decode().split("|")
        moment = dt.datetime.fromisoformat(at)
        if moment.tzinfo is None or not 0 < int(verdict_id) <= MAX_ID:
            raise ValueError
        return moment.astimezone(dt.UTC), int(verdict_id)
    except (ValueError, OverflowError, binascii.Error, UnicodeDecodeError):
        raise InputError("the cursor is not one this service issued; use next_cursor from a page") from None
