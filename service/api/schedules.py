"""Schedules of periodic inspections of a structure."""

from __future__ import annotations

from fastapi import APIRouter, BackgroundTasks, Request, Response, status

from service.api.deps import Admin, SessionDep, Viewer
from service.api.params import IdPath
from service.domain import schedules
from service.schemas import ScheduleCreate, ScheduleOut

router = APIRouter(prefix="/structures/{structure_id}/schedules", tags=["schedules"])


@router.post("", status_code=status.HTTP_201_CREATED)
def create_schedule(
    request: Request,
    background: BackgroundTasks,
    structure_id: IdPath,
    body: ScheduleCreate,
    principal: Admin,
    session: SessionDep,
) -> ScheduleOut:
    """Run an action on the structure's records every ``interval_seconds`` or on a ``cron``
    expression (UTC); each due time runs once, however many workers run."""
    schedule = schedules.create_schedule(session, principal, structure_id, body)
    background.add_task(request.app.state.jobs.wake)  # after the commit: the sweep then sees it
    return ScheduleOut.model_validate(schedule, from_attributes=True)


@router.get("")
def list_schedules(structure_id: IdPath, principal: Viewer, session: SessionDep) -> list[ScheduleOut]:
    return [
        ScheduleOut.model_validate(s, from_attributes=True)
        for s in schedules.list_schedules(session, principal, structure_id)
    ]


@router.delete("/{schedule_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_schedule(
    structure_id: IdPath, schedule_id: IdPath, principal: Admin, session: SessionDep
) -> Response:
    schedules.delete_schedule(session, principal, structure_id, schedule_id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
