"""What the jobs do, whichever backend runs them: each task takes a session, the settings and its
keyword arguments, and is idempotent (an inspection stores at most one verdict per record and
model set), so a job delivered twice changes nothing."""

from __future__ import annotations

import datetime as dt
import logging
from collections.abc import Callable

from sqlalchemy import exists, select
from sqlalchemy.orm import Session, defer

from service.config import Settings
from service.domain import inspections, modelling, refinements
from service.domain.modelling import active_fault_modes
from service.domain.schedules import RUN_SCHEDULE
from service.schemas import BaselineTrain, FaultModeTrain, RefinementCreate
from service.security import Principal, Role
from service.tables import Record, Schedule, Structure, Verdict

INSPECT_RECORD = "inspect_record"
TRAIN_MODEL = "train_model"
REFINE = "refine"

log = logging.getLogger("narxwatch.jobs")


def inspect_record(session: Session, settings: Settings, record_id: int) -> None:
    """The verdict of a stored record under its structure's active fault-mode models."""
    # Its signals are read only if it has no verdict under the active models yet.
    record = session.get(Record, record_id, options=[defer(Record.x), defer(Record.y)])
    if record is None:
        log.warning("record %s no longer exists: nothing to inspect", record_id)
        return
    structure = session.get(Structure, record.structure_id)
    assert structure is not None  # a record's structure is a foreign key
    inspections.inspect_record(session, record, structure, settings)


def run_schedule(session: Session, settings: Settings, schedule_id: int, due_at: str) -> None:
    """One due time of a schedule: its action on the structure's records."""
    schedule = session.get(Schedule, schedule_id)
    if schedule is None:
        log.info("schedule %s was deleted before its run due %s", schedule_id, due_at)
        return
    structure = session.get(Structure, schedule.structure_id)
    assert structure is not None
    if not active_fault_modes(session, structure):
        log.warning(
            "schedule %s skipped: structure %s has no active fault-mode model", schedule_id, structure.id
        )
        return
    for record_id in _records_to_inspect(session, schedule.action, structure.id):
        inspect_record(session, settings, record_id)
    log.info(
        "schedule %s (%s) ran for its time %s",
        schedule_id,
        schedule.action,
        dt.datetime.fromisoformat(due_at),
    )


def _records_to_inspect(session: Session, action: str, structure_id: int) -> list[int]:
    of_structure = select(Record.id).where(Record.structure_id == structure_id)
    if action == "reinspect_latest":
        latest = of_structure.order_by(Record.acquired_at.desc(), Record.id.desc()).limit(1)
        return list(session.scalars(latest))
    has_verdict = exists().where(Verdict.record_id == Record.id)
    return list(session.scalars(of_structure.where(~has_verdict).order_by(Record.id)))


def train_model(
    session: Session,
    settings: Settings,
    principal: dict,
    structure_id: int,
    kind: str,
    body: dict,
    token: str,
) -> None:
    """A training too large to run in its request, as the key that asked for it. The version is
    marked with the job's ``token``, so that the job run again stores no second one."""
    caller = _caller(principal)
    if modelling.version_of_job(session, structure_id, token) is not None:
        log.info("the training queued as %s has stored its version already", token)
        return
    if kind == "baseline":
        version = modelling.train_baseline(
            session, caller, structure_id, BaselineTrain.model_validate(body), settings
        )
    else:
        fault_mode = FaultModeTrain.model_validate(body)
        version = modelling.train_fault_mode(session, caller, structure_id, fault_mode, settings)
    version.training = version.training | {"job": token}
    session.commit()


def refine(
    session: Session, settings: Settings, principal: dict, structure_id: int, body: dict, token: str
) -> None:
    """A refinement too large to run in its request, as the key that asked for it; marked with
    the job's ``token`` like a queued training; commits."""
    refinement = RefinementCreate.model_validate(body)
    if refinements.refinement_of_job(session, structure_id, refinement.record_id, token) is not None:
        log.info("the refinement queued as %s has been stored already", token)
        return
    refinements.create_refinement(session, _caller(principal), structure_id, refinement, settings, job=token)


def job_principal(principal: Principal) -> dict:
    """The caller, as a queued training or refinement carries it."""
    return {
        "organisation_id": principal.organisation_id,
        "role": int(principal.role),
        "key_id": principal.key_id,
    }


def _caller(principal: dict) -> Principal:
    return Principal(principal["organisation_id"], Role(principal["role"]), principal["key_id"])


TASKS: dict[str, Callable[..., None]] = {
    INSPECT_RECORD: inspect_record,
    RUN_SCHEDULE: run_schedule,
    TRAIN_MODEL: train_model,
    REFINE: refine,
}
