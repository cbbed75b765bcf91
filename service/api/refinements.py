"""Refinements of baseline models on stored records (SPEC §7)."""

from __future__ import annotations

from fastapi import APIRouter, Request, status
from fastapi.responses import JSONResponse

from service.api.deps import Admin, SessionDep, SettingsDep, Viewer
from service.api.expensive import ACCEPTED, run_or_queue
from service.api.params import IdPath
from service.domain import refinements
from service.jobs.tasks import REFINE
from service.schemas import ModelRef, RefinementCreate, RefinementOut
from service.tables import ModelVersion, Refinement

router = APIRouter(tags=["refinements"])


@router.post(
    "/structures/{structure_id}/refinements",
    status_code=status.HTTP_201_CREATED,
    response_model=RefinementOut,
    responses=ACCEPTED,
)
def create_refinement(
    request: Request,
    structure_id: IdPath,
    body: RefinementCreate,
    principal: Admin,
    session: SessionDep,
    settings: SettingsDep,
) -> RefinementOut | JSONResponse:
    """Trace a baseline's residual on one or several records to the effects it lacks; the refined
    model is stored as a new version that is not active until activated. A refinement of long
    records is queued as a job (202)."""
    return run_or_queue(
        request,
        session,
        principal,
        refinements.refinement_cells(session, principal, structure_id, body, settings),
        lambda: refinement_out(
            refinements.create_refinement(session, principal, structure_id, body, settings)
        ),
        REFINE,
        structure_id=structure_id,
        body=body.model_dump(),
    )


@router.get("/structures/{structure_id}/refinements")
def list_refinements(structure_id: IdPath, principal: Viewer, session: SessionDep) -> list[RefinementOut]:
    """Past refinements of the structure, newest first."""
    return [refinement_out(r) for r in refinements.list_refinements(session, principal, structure_id)]


@router.get("/refinements/{refinement_id}")
def get_refinement(refinement_id: IdPath, principal: Viewer, session: SessionDep) -> RefinementOut:
    return refinement_out(refinements.get_refinement(session, principal, refinement_id))


def refinement_out(refinement: Refinement) -> RefinementOut:
    return RefinementOut(
        id=refinement.id,
        structure_id=refinement.structure_id,
        record_id=refinement.record_id,
        record_ids=refinement.record_ids_of("estimation"),
        test_record_ids=refinement.record_ids_of("test"),
        base_model=_ref(refinement.base_model) if refinement.base_model is not None else None,
        refined_model=_ref(refinement.refined_model) if refinement.refined_model is not None else None,
        created_at=refinement.created_at,
        report=refinement.report,
    )


def _ref(version: ModelVersion) -> ModelRef:
    return ModelRef(id=version.id, name=version.name, version=version.version)
