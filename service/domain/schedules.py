"""Periodic inspections: schedules of a structure, and the sweep that turns due ones into jobs.

A schedule is due at ``next_run_at``. The sweep moves that time on with a compare-and-set on its
old value and defers one ``run_schedule`` job in the same transaction, so a due time gives
exactly one job however many sweepers (service processes, workers) look at once. A sweep after
downtime runs a schedule once for everything it missed, not once per missed time. A schedule
that cannot be swept (a cron expression the database holds but croniter refuses) is logged and
tried again a minute later; it never holds up the others.
"""

from __future__ import annotations

import datetime as dt
import logging
from collections.abc import Callable
from dataclasses import dataclass

from croniter import croniter
from sqlalchemy import select, update
from sqlalchemy.orm import Session

from service.domain.errors import ConflictError, NotFoundError
from service.domain.modelling import active_baseline, active_fault_modes
from service.domain.structures import get_structure, list_owned
from service.schemas import ScheduleCreate
from service.security import Principal
from service.tables import Schedule, Structure, utcnow

RUN_SCHEDULE = "run_schedule"
RETRY_UNSWEPT = dt.timedelta(minutes=1)  # a schedule that could not be swept is looked at again after

# defer(session, task_name, organisation_id, **task_args), in the session's transaction; the job's id
Defer = Callable[..., int]

log = logging.getLogger("narxwatch.jobs")


@dataclass(frozen=True)
class Due:
    """A schedule found due, as the sweep read it: ``due_at`` is the value its claim compares."""

    schedule_id: int
    organisation_id: int
    cron: str | None
    interval_seconds: int | None
    due_at: dt.datetime


def following(
    cron: str | None, interval_seconds: int | None, due: dt.datetime, after: dt.datetime
) -> dt.datetime:
    """A schedule's first due time strictly after ``after``, given the due time ``due`` it had:
    the cron expression's next time (in UTC), or ``due`` plus whole intervals."""
    if cron is not None:
        return croniter(cron, after.astimezone(dt.UTC)).get_next(dt.datetime)
    assert interval_seconds is not None  # one of the two, by the schema
    step = dt.timedelta(seconds=interval_seconds)
    return due + max((after - due) // step + 1, 1) * step


def create_schedule(
    session: Session, principal: Principal, structure_id: int, body: ScheduleCreate
) -> Schedule:
    structure = get_structure(session, principal, structure_id)
    baseline = active_baseline(session, structure)
    if not active_fault_modes(session, structure) and (baseline is None or baseline[1] is None):
        raise ConflictError(
            f"structure {structure.name!r} has no active fault-mode model, so a schedule would have nothing "
            f"to inspect with: train one with POST /api/v1/structures/{structure.id}/models/fault-modes"
        )
    now = utcnow()
    first = following(body.cron, None, now, now) if body.cron is not None else body.first_run_at or now
    schedule = Schedule(
        structure_id=structure.id,
        action=body.action,
        interval_seconds=body.interval_seconds,
        cron=body.cron,
        next_run_at=first,
    )
    session.add(schedule)
    session.flush()
    return schedule


def list_schedules(session: Session, principal: Principal, structure_id: int) -> list[Schedule]:
    return list_owned(session, principal, Schedule, structure_id, [Schedule.id])


def delete_schedule(session: Session, principal: Principal, structure_id: int, schedule_id: int) -> None:
    structure = get_structure(session, principal, structure_id)
    schedule = session.get(Schedule, schedule_id)
    if schedule is None or schedule.structure_id != structure.id:
        raise NotFoundError("schedule", schedule_id)
    session.delete(schedule)


def sweep(session: Session, defer: Defer, now: dt.datetime | None = None) -> int:
    """Defer one ``run_schedule`` job for each schedule due at ``now``, in the caller's
    transaction; the number deferred.

    Reads first: a sweep that finds nothing due takes no write lock. Each schedule is claimed in
    a transaction of its own, and one that fails is logged and left for later, so that it never
    stops the others.
    """
    now = now or utcnow()
    deferred = 0
    for due in due_schedules(session, now):
        try:
            deferred += claim(session, defer, due, now)
        except Exception:
            session.rollback()
            log.exception(
                "schedule %s could not be swept; it is tried again in %s", due.schedule_id, RETRY_UNSWEPT
            )
            _postpone(session, due, now + RETRY_UNSWEPT)
    return deferred


def due_schedules(session: Session, now: dt.datetime) -> list[Due]:
    """The schedules due at ``now``, with their organisation; reads only (ends the read)."""
    columns = (
        Schedule.id,
        Structure.organisation_id,
        Schedule.cron,
        Schedule.interval_seconds,
        Schedule.next_run_at,
    )
    query = select(*columns).join(Structure, Structure.id == Schedule.structure_id)
    due = [
        Due(*row) for row in session.execute(query.where(Schedule.next_run_at <= now).order_by(Schedule.id))
    ]
    session.rollback()
    return due


def claim(session: Session, defer: Defer, due: Due, now: dt.datetime) -> bool:
    """Move a due schedule on and defer its job, in one transaction, if its due time is still
    the one read (a compare-and-set: another sweeper may have claimed it since); commits."""
    moved = (
        update(Schedule.__table__)
        .where(Schedule.id == due.schedule_id, Schedule.next_run_at == due.due_at)
        .values(next_run_at=following(due.cron, due.interval_seconds, due.due_at, now), last_run_at=now)
    )
    claimed = session.execute(moved).rowcount == 1
    if claimed:
        defer(
            session,
            RUN_SCHEDULE,
            due.organisation_id,
            schedule_id=due.schedule_id,
            due_at=due.due_at.isoformat(),
        )
    session.commit()
    return claimed


def _postpone(session: Session, due: Due, until: dt.datetime) -> None:
    """Move a schedule that could not be swept to ``until`` (compare-and-set, like a claim)."""
    later = (
        update(Schedule.__table__)
        .where(Schedule.id == due.schedule_id, Schedule.next_run_at == due.due_at)
        .values(next_run_at=until)
    )
    try:
        session.execute(later)
        session.commit()
    except Exception:  # the database itself is away: the next sweep sees the schedule again
        session.rollback()
        log.exception("schedule %s could not be postponed", due.schedule_id)
