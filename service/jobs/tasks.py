"""What the jobs do, whichever backend runs them: each task takes a session, the settings and its
keyword arguments, and is idempotent (an inspection stores at most one verdict per record and
model set), so a job delivered twice changes nothing.

Each record is a unit of work of its own, committed before the next: a record the models cannot
inspect (``InputError``: too short for their lags, values they cannot take) is marked with the
reason and the model set (``InspectionFailure``), so that schedules skip it until the models
change, and it never keeps the other records of a schedule run from their verdicts.
"""

from __future__ import annotations

import datetime as dt
import logging
from collections.abc import Callable, Iterable

from sqlalchemy import exists, select
from sqlalchemy.orm import Session, defer

from models.errors import InputError
from service.config import Settings
from service.db import insert_unless_exists
from service.domain import inspections, modelling, notifications, records, refinements, retention
from service.domain.errors import ConflictError
from service.domain.schedules import RUN_SCHEDULE
from service.jobs.types import JobInfo
from service.schemas import RefinementCreate
from service.security import Principal, Role
from service.tables import InspectionFailure, ModelVersion, Record, Schedule, Structure, Verdict

INSPECT_RECORD = "inspect_record"
TRAIN_MODEL = "train_model"
REFINE = "refine"

log = logging.getLogger("narxwatch.jobs")


def inspect_record(session: Session, settings: Settings, record_id: int) -> None:
    """The verdict of a stored record under its structure's active fault-mode models; commits.
    A record the models cannot inspect is marked, and the job fails with the reason."""
    # Its signals are read only if it has no verdict under the active models yet.
    record = session.get(Record, record_id, options=[defer(Record.x), defer(Record.y)])
    if record is None:
        log.warning("record %s no longer exists: nothing to inspect", record_id)
        return
    structure = session.get(Structure, record.structure_id)
    assert structure is not None  # a record's structure is a foreign key
    active = inspections.models_to_inspect_with(session, structure, bool(record.channels))
    failure = _inspect(session, settings, record, structure, active)
    if failure is not None:
        raise failure


def run_schedule(session: Session, settings: Settings, schedule_id: int, due_at: str) -> None:
    """One due time of a schedule: its action on the structure's records, each its own unit.

    Records the models cannot inspect are marked and skipped; an unexpected error on one record
    (the database away for a moment) lets the others go on, then fails the job so that it is
    retried (the records inspected meanwhile keep their verdicts and are not inspected again).
    """
    schedule = session.get(Schedule, schedule_id)
    if schedule is None:
        log.info("schedule %s was deleted before its run due %s", schedule_id, due_at)
        return
    structure = session.get(Structure, schedule.structure_id)
    assert structure is not None
    # The models are read once: every record of the run is inspected (or marked) under them.
    actives = _actives(session, structure)
    model_sets = {kind: inspections.model_set([v for v, _ in active]) for kind, active in actives.items()}
    unexpected: Exception | None = None
    marked = 0
    limit = records.acquisition_limit(settings)
    for record_id, several in _records_to_inspect(session, schedule.action, structure.id, model_sets, limit):
        record = session.get(Record, record_id)
        if record is None:  # deleted since the list was read
            continue
        try:
            marked += _inspect(session, settings, record, structure, actives[several]) is not None
        except Exception as exc:
            session.rollback()
            log.exception("schedule %s: record %s could not be inspected; going on", schedule_id, record_id)
            unexpected = unexpected or exc
    log.info(
        "schedule %s (%s) ran for its time %s; %s record(s) the models cannot inspect were marked",
        schedule_id,
        schedule.action,
        dt.datetime.fromisoformat(due_at),
        marked,
    )
    if unexpected is not None:
        raise unexpected


def _actives(session: Session, structure: Structure) -> dict[bool, inspections.Active]:
    """The active models of each kind of record (of ``several`` channels or not) the structure
    has models for. A structure may have models for one kind only (vector ones, say); a conflict
    if it has none for either, and the job fails, saying so."""
    actives: dict[bool, inspections.Active] = {}
    refusals: list[ConflictError] = []
    for several in (False, True):
        try:
            actives[several] = inspections.models_to_inspect_with(session, structure, several)
        except ConflictError as refusal:
            refusals.append(refusal)
    if not actives:
        raise refusals[0]
    return actives


def _inspect(
    session: Session, settings: Settings, record: Record, structure: Structure, active: inspections.Active
) -> InputError | None:
    """Inspect one record under the ``active`` models and commit its verdict; or, if they cannot
    inspect it, commit a mark under their model set saying why and return the refusal."""
    record_id = record.id  # read now: after the rollback below, reading it would reload the row
    model_set = inspections.model_set([version for version, _ in active])
    try:
        inspections.inspect_record(session, record, structure, settings, active)
        session.commit()
        return None
    except InputError as refusal:
        session.rollback()
        values = {"record_id": record_id, "model_set": model_set, "reason": str(refusal)}
        insert_unless_exists(session, InspectionFailure, values, ["record_id", "model_set"])
        session.commit()
        log.warning("record %s cannot be inspected with models %s: %s", record_id, model_set, refusal)
        return refusal


def _records_to_inspect(
    session: Session, action: str, structure_id: int, model_sets: dict[bool, str], limit: dt.datetime
) -> list[tuple[int, bool]]:
    """The action's records, each with its kind (of several channels or not), less those of a
    kind no active model inspects and those their kind's model set (``model_sets``) already
    failed to inspect. The latest is the latest acquired up to ``limit``
    (``records.acquisition_limit``): one stored with a date in the future, before such dates
    were refused, is not what the structure is now."""
    # Records whose signals the retention pruned cannot be inspected again.
    of_structure = select(Record.id, Record.channels).where(
        Record.structure_id == structure_id, Record.signals_pruned_at.is_(None)
    )
    if action == "reinspect_latest":
        present = of_structure.where(Record.acquired_at <= limit)
        chosen = present.order_by(Record.acquired_at.desc(), Record.id.desc()).limit(1)
    else:
        chosen = of_structure.where(~exists().where(Verdict.record_id == Record.id)).order_by(Record.id)
    candidates = [
        (record_id, bool(channels))
        for record_id, channels in session.execute(chosen)
        if bool(channels) in model_sets
    ]
    failed = select(InspectionFailure.record_id, InspectionFailure.model_set).where(
        InspectionFailure.record_id.in_([record_id for record_id, _ in candidates])
    )
    skipped = {(record_id, model_set) for record_id, model_set in session.execute(failed)}
    return [(record, kind) for record, kind in candidates if (record, model_sets[kind]) not in skipped]


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
    training = modelling.TRAININGS[kind].model_validate(body)
    version = modelling.train(session, caller, structure_id, training, settings)
    version.training = version.training | {"job": token}
    session.commit()


def models_made(session: Session, jobs: Iterable[JobInfo]) -> dict[int, ModelVersion]:
    """The model versions queued trainings stored, by job id, for those of ``jobs`` that are
    done: what a client that queued one waits for."""
    trainings = [job for job in jobs if job.task == TRAIN_MODEL and job.state == "done"]
    made = modelling.versions_of_jobs(
        session, [(job.args["structure_id"], job.args["token"]) for job in trainings]
    )
    return {job.id: made[job.args["token"]] for job in trainings if job.args["token"] in made}


def refine(
    session: Session, settings: Settings, principal: dict, structure_id: int, body: dict, token: str
) -> None:
    """A refinement too large to run in its request, as the key that asked for it; marked with
    the job's ``token`` like a queued training; commits."""
    refinement = RefinementCreate.model_validate(body)
    first = refinement.estimation_record_ids[0]
    if refinements.refinement_of_job(session, structure_id, first, token) is not None:
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


def prune_retention(session: Session, settings: Settings, organisation: int) -> None:
    """Prune an organisation under its retention policy, a batch a transaction; commits each.
    (Not ``organisation_id``: the distributed backend keeps that argument for ``GET /jobs``.)"""
    pruned = retention.prune(session, organisation)
    log.info("organisation %s pruned under its retention: %s", organisation, pruned)


TASKS: dict[str, Callable[..., None]] = {
    INSPECT_RECORD: inspect_record,
    RUN_SCHEDULE: run_schedule,
    TRAIN_MODEL: train_model,
    REFINE: refine,
    notifications.DELIVER: notifications.deliver,
    retention.PRUNE: prune_retention,
}
