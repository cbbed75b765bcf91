"""The organisation's queued work (inspections, schedule runs, trainings): what ran, what failed and why,
and what a training made."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Request

from service.api.deps import Admin, SessionDep
from service.api.params import IdPath
from service.domain.errors import NotFoundError
from service.jobs.tasks import models_made
from service.jobs.types import JobBackend, JobInfo, JobState
from service.schemas import MAX_ID, JobOut, JobPage, ModelRef
from service.tables import ModelVersion

router = APIRouter(prefix="/jobs", tags=["jobs"])

PAGE = 100


@router.get("")
def list_jobs(
    request: Request,
    principal: Admin,
    session: SessionDep,
    state: JobState | None = None,
    cursor: Annotated[int | None, Query(ge=1, le=MAX_ID)] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = PAGE,
) -> JobPage:
    """The organisation's jobs, newest first; ``state=failed`` lists those that failed for good,
    each with its reason."""
    backend: JobBackend = request.app.state.jobs
    jobs = backend.list_jobs(session, principal.organisation_id, state, limit + 1, cursor)
    page = jobs[:limit]
    made = models_made(session, page)
    items = [_out(job, made.get(job.id)) for job in page]
    return JobPage(items=items, next_cursor=page[-1].id if len(jobs) > limit else None)


@router.get("/{job_id}")
def get_job(request: Request, job_id: IdPath, principal: Admin, session: SessionDep) -> JobOut:
    backend: JobBackend = request.app.state.jobs
    job = backend.get_job(session, principal.organisation_id, job_id)
    if job is None:
        raise NotFoundError("job", job_id)
    return _out(job, models_made(session, [job]).get(job.id))


def _out(job: JobInfo, made: ModelVersion | None) -> JobOut:
    model = None if made is None else ModelRef.model_validate(made, from_attributes=True)
    return JobOut.model_validate(job, from_attributes=True).model_copy(update={"model": model})
