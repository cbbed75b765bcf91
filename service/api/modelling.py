"""Training, listing and activating model versions."""

from __future__ import annotations

from fastapi import APIRouter, status

from service.api.deps import Admin, SessionDep, Viewer
from service.api.params import IdPath
from service.domain import modelling
from service.schemas import BaselineTrain, FaultModeTrain, ModelOut
from service.tables import ModelVersion

router = APIRouter(prefix="/structures/{structure_id}/models", tags=["models"])


def model_out(version: ModelVersion) -> ModelOut:
    return ModelOut(
        id=version.id,
        kind=version.kind,  # type: ignore[arg-type]
        name=version.name,
        version=version.version,
        active=version.active,
        created_at=version.created_at,
        terms=version.training.get("terms", []),
        training=version.training,
        statistics=version.statistics,
    )


@router.post("/baseline", status_code=status.HTTP_201_CREATED)
def train_baseline(
    structure_id: IdPath, body: BaselineTrain, principal: Admin, session: SessionDep
) -> ModelOut:
    """Identify the healthy structure's NARX from stored records (default: SPEC §2's 8 terms)."""
    version = modelling.train_baseline(session, principal, structure_id, body)
    return model_out(version)


@router.post("/fault-modes", status_code=status.HTTP_201_CREATED)
def train_fault_mode(
    structure_id: IdPath, body: FaultModeTrain, principal: Admin, session: SessionDep
) -> ModelOut:
    """Identify a fault mode as a functional NARX; the new version becomes the active one."""
    version = modelling.train_fault_mode(session, principal, structure_id, body)
    return model_out(version)


@router.get("")
def list_models(structure_id: IdPath, principal: Viewer, session: SessionDep) -> list[ModelOut]:
    return [model_out(v) for v in modelling.list_models(session, principal, structure_id)]


@router.post("/{model_id}/activate")
def activate_model(structure_id: IdPath, model_id: IdPath, principal: Admin, session: SessionDep) -> ModelOut:
    """Make this version the active one of its name."""
    version = modelling.activate_model(session, principal, structure_id, model_id)
    return model_out(version)
