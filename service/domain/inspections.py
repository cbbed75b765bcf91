"""Inspecting stored records and persisting every verdict exactly once per model set."""

from __future__ import annotations

from dataclasses import asdict

from sqlalchemy import insert, select
from sqlalchemy.orm import Session, selectinload

from models.inspection import ModeResult, inspect
from service.config import Settings
from service.db import insert_unless_exists
from service.domain.errors import ConflictError, NotFoundError
from service.domain.modelling import active_fault_modes
from service.domain.records import signals
from service.domain.structures import get_structure
from service.schemas import ModelRef, VerdictOut
from service.security import Principal
from service.tables import Record, Structure, Verdict, VerdictModel


def inspect_record(
    session: Session, record: Record, structure: Structure, settings: Settings
) -> tuple[Verdict, bool]:
    """The verdict of a record under the structure's active fault-mode models; True when new.

    A record already inspected with the same model versions keeps its verdict, so repeating
    an inspection (or a redelivered job) changes nothing.
    """
    active = active_fault_modes(session, structure)
    if not active:
        raise ConflictError(
            f"structure {structure.name!r} has no active fault-mode model: train one with "
            f"POST /api/v1/structures/{structure.id}/models/fault-modes"
        )
    model_set = ",".join(str(version.id) for version, _ in sorted(active, key=lambda item: item[0].id))
    existing = _find(session, record.id, model_set)
    if existing is not None:
        return existing, False
    x, y = signals(record)
    result = inspect(x, y, [model for _, model in active], alpha=settings.alpha, lags=settings.lags)
    values = dict(
        record_id=record.id,
        structure_id=structure.id,
        acquired_at=record.acquired_at,
        model_set=model_set,
        status=result.status,
        fault_detected=result.fault_detected,
        fault_mode=result.fault_mode,
        reference_mode=result.reference_mode,
        k_hat=result.k_hat,
        sigma_k=result.sigma_k,
        interval_low=result.interval[0] if result.interval else None,
        interval_high=result.interval[1] if result.interval else None,
        alpha=result.alpha,
        lags=result.lags,
        n_samples=result.n_samples,
        z_critical=result.z_critical,
        q_critical_detection=result.q_critical_detection,
        detected_by=list(result.detected_by),
        modes=[asdict(mode) for mode in result.modes],
    )
    verdict_id = insert_unless_exists(session, Verdict, values, ["record_id", "model_set"])
    if verdict_id is None:  # the same inspection finished concurrently: keep the first
        found = _find(session, record.id, model_set)
        if found is None:
            raise RuntimeError(f"verdict of record {record.id} conflicted but cannot be found")
        return found, False
    session.execute(
        insert(VerdictModel), [{"verdict_id": verdict_id, "model_version_id": v.id} for v, _ in active]
    )
    return session.get_one(Verdict, verdict_id, options=[selectinload(Verdict.models)]), True


def get_verdict(session: Session, principal: Principal, verdict_id: int) -> Verdict:
    verdict = session.get(Verdict, verdict_id, options=[selectinload(Verdict.models)])
    if verdict is None:
        raise NotFoundError("verdict", verdict_id)
    try:
        get_structure(session, principal, verdict.structure_id)
    except NotFoundError:
        raise NotFoundError("verdict", verdict_id) from None
    return verdict


def verdict_out(verdict: Verdict) -> VerdictOut:
    interval = (
        (verdict.interval_low, verdict.interval_high)
        if verdict.interval_low is not None and verdict.interval_high is not None
        else None
    )
    return VerdictOut(
        id=verdict.id,
        record_id=verdict.record_id,
        structure_id=verdict.structure_id,
        acquired_at=verdict.acquired_at,
        created_at=verdict.created_at,
        status=verdict.status,  # type: ignore[arg-type]
        fault_detected=verdict.fault_detected,
        fault_mode=verdict.fault_mode,
        reference_mode=verdict.reference_mode,
        k_hat=verdict.k_hat,
        sigma_k=verdict.sigma_k,
        interval=interval,
        alpha=verdict.alpha,
        lags=verdict.lags,
        n_samples=verdict.n_samples,
        z_critical=verdict.z_critical,
        q_critical_detection=verdict.q_critical_detection,
        detected_by=verdict.detected_by,
        modes=[ModeResult(**mode) for mode in verdict.modes],
        model_versions=[
            ModelRef(id=m.id, name=m.name, version=m.version)
            for m in sorted(verdict.models, key=lambda m: m.name)
        ],
    )


def _find(session: Session, record_id: int, model_set: str) -> Verdict | None:
    query = (
        select(Verdict)
        .where(Verdict.record_id == record_id, Verdict.model_set == model_set)
        .options(selectinload(Verdict.models))
    )
    return session.scalar(query)
