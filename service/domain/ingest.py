"""Ingesting a record: checked, stored once by content, inspected or queued on request."""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from numpy.typing import ArrayLike
from sqlalchemy.orm import Session

from models.baseline_choice import NONLINEAR_DEGREE
from models.errors import InputError
from models.free_run_inspection import FreeRunMode
from models.pooled import PooledModel
from models.signals import minimum_samples
from models.terms import max_degree
from models.vector import VectorFNARX
from recordfiles.conditions import Condition
from service.config import Settings
from service.domain import alarms, inspections, records, structures
from service.domain.modelling import active_fault_modes
from service.security import Principal
from service.tables import ModelVersion, Record, Structure, Verdict

QueueInspection = Callable[[Session, int], None]  # queue(session, record_id), in its transaction


@dataclass(frozen=True)
class Ingested:
    record: Record
    created: bool  # False when the same data had been stored before
    # Computed now (inspect), or, when queueing, the one the active models gave before.
    verdict: Verdict | None
    queued: bool  # an inspection job was queued


def ingest_record(
    session: Session,
    principal: Principal,
    settings: Settings,
    structure_id: int,
    x: ArrayLike,
    y: ArrayLike,
    fs: float | None,
    acquired_at: dt.datetime | None,
    inspect: bool,
    queue: QueueInspection | None = None,
    conditions: Sequence[Condition] = (),
    channels: Sequence[str] = (),
) -> Ingested:
    """Store a record with its (checked) conditions and, with ``inspect``, its verdict under the
    active models at those conditions, or through ``queue`` an inspection job in the same transaction
    (committed by the caller).

    Everything that can refuse the record runs before the first write, cheapest first: the
    sampling rate and the acquisition time (none later than the server's clock allows), then one
    check of the signals against what they will face (the inspection's own check with
    ``inspect``, the same check without the inspection when queueing, so that a queued job
    cannot fail on what the upload could have refused, and the shortest storable record
    otherwise). The verdict is computed before the first write too, so the write lock
    (SQLite's, and the writer gate in front of it) is held only for the inserts and their commit.
    A record queued again is queued only when it has no verdict from the active models. A record
    of several ``channels`` (checked, naming y's columns) is inspected by the active vector models,
    whose channels it must have.
    """
    structure = structures.get_structure(session, principal, structure_id)
    rate = records.checked_rate(structure, fs)
    acquired_at = records.checked_acquired_at(acquired_at, settings)
    evaluation = None
    active: list[ModelVersion] = []
    if inspect or queue is not None:
        models = inspections.models_to_inspect_with(session, structure, bool(channels))
        values = records.condition_values(conditions)
        if not values and any(isinstance(model, PooledModel) for _, model in models):
            # Data stored before and sent again stating no conditions are that record, to be
            # judged at the conditions it was stored with (records.store_record).
            values = records.condition_values(records.stored_conditions(session, structure, x, y, rate))
    if inspect or queue is not None:
        inspections.check_inspection_cost(models, len(x), settings, queued=not inspect)  # type: ignore[arg-type]
    if inspect:
        evaluation = inspections.evaluate(models, settings, x, y, values, channels)
    elif queue is not None:
        if channels:  # checked as its job will check it; stored in the channel order uploaded
            inspections.vector_record(models, x, y, channels, settings.lags)
        else:
            x, y = inspections.checked_to_queue(models, x, y, values, settings.lags)
        active = [version for version, _ in models]
    else:
        degree = 1 if channels else _degree_to_hold(session, structure)
        x, y = records.checked_signals(x, y, channels, minimum_samples(settings.lags), degree)
    if evaluation is not None:
        alarms.lock(session, structure.id)  # before the state row that storing the record locks
    record, created = records.store_record(session, structure, x, y, rate, acquired_at, conditions, channels)
    verdict = (
        inspections.store_verdict(session, record, structure, evaluation, settings, created)
        if evaluation
        else None
    )
    queued = False
    if queue is not None:
        verdict = None if created else inspections.verdict_under(session, record.id, active)
        if verdict is None:
            queue(session, record.id)
            queued = True
    return Ingested(record, created, verdict, queued)


@dataclass(frozen=True)
class SetRecord:
    """A record of a set (a file of realisations side by side), named as refusals name it."""

    label: str  # its signals, "(F2, A2)"
    x: ArrayLike
    y: ArrayLike
    fs: float | None
    conditions: Sequence[Condition] = ()


def ingest_record_set(
    session: Session,
    settings: Settings,
    structure: Structure,
    members: Sequence[SetRecord],
    acquired_at: dt.datetime | None,
) -> list[Ingested]:
    """Store the records of a set on ``structure`` (looked up for the caller's key), not inspected
    (they are a benchmark's estimation and validation data), in their order: all of them or, when
    one is refused, none, the refusal naming it.

    Every record is checked, as :func:`ingest_record` checks one it does not inspect, before the
    first is written, against one look-up of the degree its records must hold: the write lock is
    then held for the inserts alone, not for a hundred records' checks.
    """
    acquired_at = records.checked_acquired_at(acquired_at, settings)
    degree = _degree_to_hold(session, structure)
    checked = []
    for member in members:
        try:
            rate = records.checked_rate(structure, member.fs)
            x, y = records.checked_signals(member.x, member.y, (), minimum_samples(settings.lags), degree)
        except InputError as exc:
            raise InputError(
                f"the record {member.label} of the set: {exc}; no record of the set was stored"
            ) from None
        checked.append((x, y, rate, member.conditions))
    return [
        Ingested(*records.store_record(session, structure, x, y, rate, acquired_at, conditions), None, False)
        for x, y, rate, conditions in checked
    ]


def _degree_to_hold(session: Session, structure: Structure) -> int:
    """The term degree a stored record's values must fit: the active fault-mode models' highest,
    or, before the structure has any, the highest a baseline's chosen terms may have
    (:data:`models.baseline_choice.NONLINEAR_DEGREE`). A record only its later inspection would
    refuse for its magnitude is refused now."""
    active = [
        model for _, model in active_fault_modes(session, structure) if not isinstance(model, VectorFNARX)
    ]
    # A sensor-noise mode's terms are its FNARX's.
    fitted = [model.model if isinstance(model, FreeRunMode) else model for model in active]
    terms = [term for model in fitted for term in model.terms]
    return max_degree(terms) if terms else NONLINEAR_DEGREE
