"""Periodic inspections: schedules of a structure, and the sweep that turns due ones into jobs.

A schedule is due at ``next_run_at``. The sweep moves that time on with a compare-and-set on its
old value and defers one ``run_schedule`` job in the same transaction, so a due time gives
exactly one job however many sweepers (service processes, workers) look at once. A sweep after
downtime runs a schedule once for everything it missed, not once per missed time.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable

from croniter import croniter
from sqlalchemy import select, update
from sqlalchemy.orm import Session

from service.domain.errors import NotFoundError
from service.domain.structures import get_structure
from service.schemas import ScheduleCreate
from service.security import Principal
from service.tables import Schedule, utcnow

RUN_SCHEDULE = "run_schedule"

Defer = Callable[..., None]  # defer(session, task_name, **task_args), in the session's transaction


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
    structure = get_structure(session, principal, structure_id)
    query = select(Schedule).where(Schedule.structure_id == structure.id).order_by(Schedule.id)
    return list(session.scalars(query))


def delete_schedule(session: Session, principal: Principal, structure_id: int, schedule_id: int) -> None:
    structure = get_structure(session, principal, structure_id)
    schedule = session.get(Schedule, schedule_id)
    if schedule is None or schedule.structure_id != structure.id:
        raise NotFoundError("schedule", schedule_id)
    session.delete(schedule)


def sweep(session: Session, defer: Defer, now: dt.datetime | None = None) -> int:
    """Defer one ``run_schedule`` job for each schedule due at ``now``, in the caller's
    transaction; the number deferred.

    Reads first: a sweep that finds nothing due takes no write lock.
    """
    now = now or utcnow()
    columns = (Schedule.id, Schedule.cron, Schedule.interval_seconds, Schedule.next_run_at)
    due = session.execute(select(*columns).where(Schedule.next_run_at <= now).order_by(Schedule.id)).all()
    deferred = 0
    for schedule_id, cron, interval_seconds, due_at in due:
        claim = (
            update(Schedule.__table__)
            .where(Schedule.id == schedule_id, Schedule.next_run_at == due_at)
            .values(next_run_at=following(cron, interval_seconds, due_at, now), last_run_at=now)
        )
        if session.execute(claim).rowcount == 1:  # else another sweeper has just moved it on
            defer(session, RUN_SCHEDULE, schedule_id=schedule_id, due_at=due_at.isoformat())
            deferred += 1
    return deferred
