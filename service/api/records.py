"""Record uploads, inspections and verdicts."""

from __future__ import annotations

import datetime as dt
from enum import StrEnum
from typing import Annotated

from fastapi import APIRouter, BackgroundTasks, Query, Request, Response, status
from fastapi.concurrency import run_in_threadpool
from sqlalchemy.orm import Session

from recordfiles.channels import MAX_CHANNELS
from recordfiles.reader import NAMING_HELP, Layout
from service.api.deps import Ingest, SessionDep, SettingsDep, Viewer
from service.api.expensive import BUSY, UPLOADS_BUSY, slot
from service.api.params import IdPath, utc
from service.api.uploads import (
    RECORD_SET_BODY,
    REQUEST_BODY,
    Upload,
    parse_upload,
    parse_upload_set,
    signal_layout,
)
from service.config import Settings
from service.db import transaction
from service.domain import inspections, structures
from service.domain.ingest import Ingested, QueueInspection, SetRecord, ingest_record, ingest_record_set
from service.jobs.tasks import INSPECT_RECORD
from service.jobs.types import JobBackend
from service.schemas import RecordOut, VerdictOut
from service.security import Principal

router = APIRouter(tags=["records"])

SIGNAL_HELP = "The CSV column or MAT variable that holds {role}; " + NAMING_HELP
SET_SIGNAL_HELP = (
    "The CSV column group or MAT matrix that holds {role} of every record of the set, or one column or "
    "variable for a set of one record; " + NAMING_HELP
)
NAME_LENGTH = 200
# UPLOAD_SESSIONS: an upload opens its session, writes and commits in the one worker thread that
# parsed and inspected it, rather than taking the request's (SessionDep). On SQLite a write holds
# the file's writer gate until its commit, and a commit reached back through the event loop, a few
# milliseconds when the loop is receiving other uploads' bodies, held every other writer back; and
# each trip of the request's session through the thread pool (opened, closed) costs an upload
# more than its statements.


class InspectMode(StrEnum):
    false = "false"
    true = "true"
    queue = "queue"


@router.post(
    "/structures/{structure_id}/records",
    status_code=status.HTTP_201_CREATED,
    openapi_extra={"requestBody": REQUEST_BODY},
    responses=UPLOADS_BUSY
    | {
        200: {
            "model": RecordOut,
            "description": "The same data had been uploaded before (with inspect=queue: and the active "
            "models' verdict on it, which is returned instead of queueing it again)",
        },
        202: {"model": RecordOut, "description": "Stored, and its inspection queued (inspect=queue)"},
    },
)
async def upload_record(
    request: Request,
    response: Response,
    background: BackgroundTasks,
    structure_id: IdPath,
    principal: Ingest,
    settings: SettingsDep,
    inspect: Annotated[
        InspectMode,
        Query(
            description="true: run the inspection chain and return the verdict; queue: queue it and "
            "answer 202 (the verdict appears in the history); false: store only"
        ),
    ] = InspectMode.false,
    acquired_at: Annotated[
        dt.datetime | None, Query(description="Acquisition time for CSV/NPZ/MAT bodies (ISO 8601 with zone)")
    ] = None,
    x: Annotated[str, Query(max_length=NAME_LENGTH, description=SIGNAL_HELP.format(role="x"))] = "x",
    y: Annotated[
        list[str],
        Query(
            description=SIGNAL_HELP.format(role="y")
            + f"; given 2 to {MAX_CHANNELS} times, the CSV columns, NPZ members or MAT variables that hold "
            "a record's response channels, named so"
        ),
    ] = ["y"],  # noqa: B006 - FastAPI copies a default, never shares it
) -> RecordOut:
    """Upload a record as JSON, CSV, NPZ or MAT; a re-upload of the same data returns the stored one."""
    # Nothing is queried before the body has arrived: a slow client holds no connection.
    body = await request.body()  # bounded by the BodyLimitMiddleware
    queue = (
        _queue_inspection(request.app.state.jobs, principal.organisation_id)
        if inspect is InspectMode.queue
        else None
    )
    content_type = request.headers.get("content-type", "")
    layout = signal_layout(x, y, NAME_LENGTH)

    def parse_and_ingest() -> Ingested:
        upload = parse_upload(body, content_type, acquired_at, settings.max_upload_bytes, layout)
        with transaction(request.app.state.sessions) as session:  # see UPLOAD_SESSIONS
            return _ingest(
                upload, session, principal, settings, structure_id, inspect is InspectMode.true, queue
            )

    # Parsing a large body and checking it take a good part of a second: never on the event loop.
    ingested = await request.app.state.uploads.run(parse_and_ingest)
    if ingested.queued:
        response.status_code = status.HTTP_202_ACCEPTED
        background.add_task(request.app.state.jobs.wake)  # after the commit: the worker then sees it
    elif not ingested.created:
        response.status_code = status.HTTP_200_OK
    return _record_out(ingested)


@router.post(
    "/structures/{structure_id}/record-sets",
    status_code=status.HTTP_201_CREATED,
    openapi_extra={"requestBody": RECORD_SET_BODY},
    responses=UPLOADS_BUSY
    | {200: {"model": list[RecordOut], "description": "Every record of the set had been uploaded before"}},
)
async def upload_record_set(
    request: Request,
    response: Response,
    structure_id: IdPath,
    principal: Ingest,
    settings: SettingsDep,
    acquired_at: Annotated[
        dt.datetime | None, Query(description="Acquisition time of every record (ISO 8601 with zone)")
    ] = None,
    x: Annotated[str, Query(max_length=NAME_LENGTH, description=SET_SIGNAL_HELP.format(role="x"))] = "x",
    y: Annotated[str, Query(max_length=NAME_LENGTH, description=SET_SIGNAL_HELP.format(role="y"))] = "y",
) -> list[RecordOut]:
    """Upload a file of realisations side by side as its records: where x and y each name a group
    of k signals (CSV columns under one header cell, k×N MAT matrices), the k records (x1, y1) …
    (xk, yk), in that order, stored in one transaction — all of them or, if any is refused, none.
    A record uploaded before is returned as stored. Records of a set are not inspected here: they
    are a benchmark's estimation and validation data (POST .../refinements takes their ids)."""
    body = await request.body()  # bounded by the BodyLimitMiddleware
    layout = signal_layout(x, [y], NAME_LENGTH)
    # A body is parsed only for a structure the key may upload to, looked up in a session of its
    # own: the request's would hold a pooled connection while the parse waits for its turn.
    await run_in_threadpool(_check_structure, request, principal, structure_id)
    content_type = request.headers.get("content-type", "")

    def parse_and_ingest() -> list[Ingested]:
        uploads = parse_upload_set(body, content_type, acquired_at, settings.max_upload_bytes, layout)
        with transaction(request.app.state.sessions) as session:  # see UPLOAD_SESSIONS
            return _ingest_set(uploads, acquired_at, session, principal, settings, structure_id)

    ingested = await request.app.state.uploads.run(parse_and_ingest)
    if not any(item.created for item in ingested):
        response.status_code = status.HTTP_200_OK
    return [_record_out(item) for item in ingested]


@router.post("/records/{record_id}/inspect", responses=BUSY)
def inspect_record(
    request: Request, record_id: IdPath, principal: Ingest, session: SessionDep, settings: SettingsDep
) -> VerdictOut:
    """Inspect a stored record with every active fault-mode model of its structure; a verdict
    it already has under those models is returned as it is."""
    with slot(request, principal):
        verdict = inspections.inspect_stored(session, principal, record_id, settings)
    return VerdictOut.model_validate(verdict, from_attributes=True)


@router.get("/verdicts/{verdict_id}")
def get_verdict(verdict_id: IdPath, principal: Viewer, session: SessionDep) -> VerdictOut:
    verdict = inspections.get_verdict(session, principal, verdict_id)
    return VerdictOut.model_validate(verdict, from_attributes=True)


def _ingest(
    upload: Upload,
    session: Session,
    principal: Principal,
    settings: Settings,
    structure_id: int,
    inspect: bool,
    queue: QueueInspection | None,
) -> Ingested:
    return ingest_record(
        session,
        principal,
        settings,
        structure_id,
        upload.x,
        upload.y,
        upload.fs,
        utc(upload.acquired_at, "acquired_at"),
        inspect,
        queue,
        upload.conditions,
        upload.channels,
    )


def _check_structure(request: Request, principal: Principal, structure_id: int) -> None:
    with transaction(request.app.state.sessions) as session:
        structures.get_structure(session, principal, structure_id)


def _ingest_set(
    uploads: tuple[tuple[Layout, Upload], ...],
    acquired_at: dt.datetime | None,
    session: Session,
    principal: Principal,
    settings: Settings,
    structure_id: int,
) -> list[Ingested]:
    structure = structures.get_structure(session, principal, structure_id)
    members = [
        SetRecord(f"({signals.x}, {signals.y})", upload.x, upload.y, upload.fs, upload.conditions)
        for signals, upload in uploads
    ]
    return ingest_record_set(session, settings, structure, members, utc(acquired_at, "acquired_at"))


def _queue_inspection(jobs: JobBackend, organisation_id: int) -> QueueInspection:
    return lambda session, record_id: jobs.defer(
        session, INSPECT_RECORD, organisation_id, record_id=record_id
    )


def _record_out(ingested: Ingested) -> RecordOut:
    record, verdict = ingested.record, ingested.verdict
    return RecordOut(
        id=record.id,
        structure_id=record.structure_id,
        fs=record.fs,
        n_samples=record.n_samples,
        acquired_at=record.acquired_at,
        created_at=record.created_at,
        sha256=record.sha256,
        conditions=record.conditions,
        channels=record.channels,
        created=ingested.created,
        signals_pruned_at=record.signals_pruned_at,
        verdict=VerdictOut.model_validate(verdict, from_attributes=True) if verdict is not None else None,
    )
