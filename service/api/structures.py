"""Structures, their fault history and summary."""

from __future__ import annotations

import datetime as dt
from typing import Annotated

from fastapi import APIRouter, Query, Request, Response, status

from service.api.deps import Admin, SessionDep, SettingsDep, Viewer
from service.api.params import IdPath, utc
from service.domain import fleet, history, structures
from service.schemas import (
    MODE_NAME_LENGTH,
    MODE_NAME_PATTERN,
    NAME_PATTERN,
    STRUCTURE_NAME_LENGTH,
    StructureCreate,
    StructureListed,
    StructureOut,
    StructureUpdate,
    Summary,
    VerdictPage,
)

router = APIRouter(prefix="/structures", tags=["structures"])


@router.post("", status_code=status.HTTP_201_CREATED)
def create_structure(body: StructureCreate, principal: Admin, session: SessionDep) -> StructureOut:
    structure = structures.create_structure(session, principal, body)
    return StructureOut.model_validate(structure, from_attributes=True)


@router.get("")
def list_structures(
    request: Request,
    response: Response,
    principal: Viewer,
    session: SessionDep,
    status_filter: Annotated[
        fleet.Standing | None,
        Query(alias="status", description="Only structures whose latest verdict has this status"),
    ] = None,
    name: Annotated[
        str | None,
        Query(
            max_length=STRUCTURE_NAME_LENGTH,
            pattern=NAME_PATTERN,
            description="Only names containing this, in any case",
        ),
    ] = None,
    cursor: Annotated[str | None, Query(max_length=200, description="From the `next` link of a page")] = None,
    limit: Annotated[int, Query(ge=1, le=fleet.MAX_PAGE_SIZE)] = fleet.PAGE_SIZE,
) -> list[StructureListed]:
    """Your organisation's structures in order of id, each with its latest status and since when it
    holds, a page at a time; a header
    `Link: </api/v1/structures?…&cursor=…>; rel="next"` gives the next page, and none the last."""
    page = fleet.fleet(session, principal, standing=status_filter, name=name, cursor=cursor, limit=limit)
    if page.next_cursor is not None:
        following = request.url.include_query_params(cursor=page.next_cursor)
        response.headers["Link"] = f'<{following.path}?{following.query}>; rel="next"'
    return [_listed(row) for row in page.items]


@router.get("/{structure_id}")
def get_structure(structure_id: IdPath, principal: Viewer, session: SessionDep) -> StructureOut:
    structure = structures.get_structure(session, principal, structure_id)
    return StructureOut.model_validate(structure, from_attributes=True)


@router.patch("/{structure_id}")
def update_structure(
    structure_id: IdPath, body: StructureUpdate, principal: Admin, session: SessionDep
) -> StructureOut:
    """Change the structure's name, description or what its signals measure: the fields sent
    change, the others stay (its fs never: its records were stored at it). A name another of your
    structures has is a conflict (409).

    Before the structure has records or models, a declaration may change or be withdrawn (null).
    After, it may only be completed: declared where it was not, or given its unit where none was
    stated. Changing or withdrawing it is refused (409), since the stored records and the models'
    coefficients are in the units first declared; create another structure for signals measured
    otherwise. Nothing is changed when any part of the request is refused."""
    structure = structures.update_structure(session, principal, structure_id, body)
    return StructureOut.model_validate(structure, from_attributes=True)


@router.get("/{structure_id}/verdicts")
def fault_history(
    structure_id: IdPath,
    principal: Viewer,
    session: SessionDep,
    settings: SettingsDep,
    start: Annotated[
        dt.datetime | None, Query(description="Acquired at or after (ISO 8601 with zone)")
    ] = None,
    end: Annotated[dt.datetime | None, Query(description="Acquired before (ISO 8601 with zone)")] = None,
    status_filter: Annotated[history.Status | None, Query(alias="status")] = None,
    fault_mode: Annotated[str | None, Query(max_length=MODE_NAME_LENGTH, pattern=MODE_NAME_PATTERN)] = None,
    cursor: Annotated[str | None, Query(max_length=200)] = None,
    limit: Annotated[int | None, Query(ge=1, le=1000)] = None,
) -> VerdictPage:
    """The structure's verdicts, newest first, with filters and cursor pagination."""
    page = history.history(
        session,
        principal,
        structure_id,
        start=utc(start, "start"),
        end=utc(end, "end"),
        status=status_filter,
        fault_mode=fault_mode,
        cursor=cursor,
        limit=limit or settings.history_page_size,
    )
    return VerdictPage.model_validate(page, from_attributes=True)


@router.get("/{structure_id}/summary")
def structure_summary(structure_id: IdPath, principal: Viewer, session: SessionDep) -> Summary:
    """Counts by status, the latest verdict and the k̂ trend."""
    return Summary.model_validate(history.summary(session, principal, structure_id), from_attributes=True)


def _listed(row: fleet.StructureStatus) -> StructureListed:
    out = StructureOut.model_validate(row.structure, from_attributes=True)
    return StructureListed(**dict(out), status=row.status, since=row.since)
