"""Training, listing and activating model versions."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from fastapi import APIRouter, Depends, Request, status
from fastapi.responses import JSONResponse
from sqlalchemy.orm import Session

from service.api.deps import Admin, SessionDep, SettingsDep, Viewer
from service.api.expensive import ACCEPTED, run_or_queue
from service.api.params import IdPath
from service.config import Settings
from service.domain import modelling
from service.jobs.tasks import TRAIN_MODEL
from service.schemas import (
    BaselineTrain,
    FaultModeTrain,
    ModelOut,
    PooledBaselineTrain,
    PooledFaultModeTrain,
    Train,
    VectorFaultModeTrain,
)
from service.security import Principal
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


@dataclass(frozen=True)
class _Training:
    """What runs a training for a request: who asks, in which session, under which settings."""

    request: Request
    principal: Principal
    session: Session
    settings: Settings

    def __call__(self, structure_id: int, body: Train) -> ModelOut | JSONResponse:
        """Run a training within the request, in one of the organisation's slots, or queue it."""
        request, principal, session, settings = self.request, self.principal, self.session, self.settings
        return run_or_queue(
            request,
            session,
            principal,
            modelling.training_cells(session, principal, structure_id, body, settings),
            lambda: model_out(modelling.train(session, principal, structure_id, body, settings)),
            TRAIN_MODEL,
            structure_id=structure_id,
            kind=modelling.training_kind(body),
            body=body.model_dump(),
        )


def _training(request: Request, principal: Admin, session: SessionDep, settings: SettingsDep) -> _Training:
    return _Training(request, principal, session, settings)


# A training route's caller, session and settings: what it needs beside its structure and body.
Trainer = Annotated[_Training, Depends(_training)]


@router.post("/baseline", status_code=status.HTTP_201_CREATED, response_model=ModelOut, responses=ACCEPTED)
def train_baseline(structure_id: IdPath, body: BaselineTrain, train: Trainer) -> ModelOut | JSONResponse:
    """Identify the healthy structure's NARX from stored records, its terms as given or, without
    them, chosen for the structure from these records (training.choice says how); a large training
    is queued as a job (202)."""
    return train(structure_id, body)


@router.post("/fault-modes", status_code=status.HTTP_201_CREATED, response_model=ModelOut, responses=ACCEPTED)
def train_fault_mode(structure_id: IdPath, body: FaultModeTrain, train: Trainer) -> ModelOut | JSONResponse:
    """Identify a fault mode as a functional NARX, its terms as given or the active baseline's; the
    new version becomes the active one. A large training is queued as a job (202)."""
    return train(structure_id, body)


@router.post(
    "/pooled-baseline", status_code=status.HTTP_201_CREATED, response_model=ModelOut, responses=ACCEPTED
)
def train_pooled_baseline(
    structure_id: IdPath, body: PooledBaselineTrain, train: Trainer
) -> ModelOut | JSONResponse:
    """Identify a pooled baseline, its coefficients functions of the operating conditions the
    records were stored with; it becomes the active baseline. A large training is queued (202)."""
    return train(structure_id, body)


@router.post(
    "/pooled-fault-modes", status_code=status.HTTP_201_CREATED, response_model=ModelOut, responses=ACCEPTED
)
def train_pooled_fault_mode(
    structure_id: IdPath, body: PooledFaultModeTrain, train: Trainer
) -> ModelOut | JSONResponse:
    """Identify a pooled fault mode, its coefficients functions of the operating conditions and k;
    the new version becomes the active one. A large training is queued (202)."""
    return train(structure_id, body)


@router.post(
    "/vector-fault-modes", status_code=status.HTTP_201_CREATED, response_model=ModelOut, responses=ACCEPTED
)
def train_vector_fault_mode(
    structure_id: IdPath, body: VectorFaultModeTrain, train: Trainer
) -> ModelOut | JSONResponse:
    """Identify a vector fault mode from records of several channels (one equation per channel over
    every channel's lags, coefficients functions of k); it inspects the structure's records of those
    channels. The new version becomes the active one. A large training is queued (202)."""
    return train(structure_id, body)


@router.get("")
def list_models(structure_id: IdPath, principal: Viewer, session: SessionDep) -> list[ModelOut]:
    return [model_out(v) for v in modelling.list_models(session, principal, structure_id)]


@router.post("/{model_id}/activate")
def activate_model(structure_id: IdPath, model_id: IdPath, principal: Admin, session: SessionDep) -> ModelOut:
    """Make this version the active one of its name."""
    version = modelling.activate_model(session, principal, structure_id, model_id)
    return model_out(version)
