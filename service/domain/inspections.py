"""Inspecting stored records and persisting every verdict exactly once per model set."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from sqlalchemy import insert, select
from sqlalchemy.orm import Session, defer, selectinload

from models.errors import InputError
from models.fnarx import FNARX
from models.free_run_inspection import FreeRunMode, checked_for_free_run, inspect_free_run
from models.inspection import Verdict as InspectionVerdict
from models.inspection import checked_for_inspection, inspect
from models.narx import NARX
from models.novelty import NoveltyVerdict, checked_for_judgement, judge_record
from models.pooled import PooledModel, baseline_verdict, check_baseline
from models.signals import minimum_samples
from models.vector import VectorFNARX, inspect_vector, vector_verdict
from recordfiles import channels as channel_rules
from service.config import Settings
from service.db import insert_unless_exists
from service.domain import alarms, fleet
from service.domain.errors import ConflictError
from service.domain.modelling import NoveltyBaseline, active_baseline, active_fault_modes
from service.domain.records import (
    acquisition_limit,
    checked_signals,
    condition_values,
    signals,
)
from service.domain.structures import get_owned, get_structure
from service.security import Principal
from service.tables import ModelVersion, Record, Structure, Verdict, VerdictModel

# A verdict's model versions as its answer names them (id, name, version), never their
# documents: those can be large, and no verdict answer or history page shows them.
MODEL_REFS = selectinload(Verdict.models).load_only(ModelVersion.id, ModelVersion.name, ModelVersion.version)
# The conditions of a verdict's record, which its answer shows too: with MODEL_REFS, everything
# a VerdictOut reads beyond the verdict's own row, loaded for a page of verdicts in two queries.
CONDITIONS = selectinload(Verdict.conditions)


@dataclass(frozen=True)
class Evaluation:
    """A verdict computed but not yet stored, with the model versions that gave it; ``novelty``
    the figures of a healthy baseline's judgement alone (None for the others)."""

    versions: list[ModelVersion]
    model_set: str
    result: InspectionVerdict
    novelty: NoveltyVerdict | None = None


Active = list[tuple[ModelVersion, FNARX | PooledModel | VectorFNARX | FreeRunMode | NoveltyBaseline]]


def evaluate(
    active: Active,
    settings: Settings,
    x: ArrayLike,
    y: ArrayLike,
    conditions: Mapping[str, float],
    channels: Sequence[str] = (),
) -> Evaluation:
    """A record's verdict under the ``active`` models (:func:`models_to_inspect_with`) at its
    ``conditions``: the fault-mode chain (pooled modes evaluated there; the free-run chain for
    sensor-noise modes, ``models.free_run_inspection``), or, for a structure
    monitored by a pooled baseline alone, that baseline's check there, or by a plain baseline
    alone, its judgement (``models.novelty``: healthy or anomaly, at the false-alarm rate
    ``settings.alpha``); for a record of several ``channels``, the vector inspection
    (:func:`vector_record`). Reads, never writes: kept apart from storing so that an upload
    computes its verdict before its first write (SQLite then holds its write lock only for the
    inserts)."""
    models = [model for _, model in active]
    versions = [version for version, _ in active]
    if isinstance(models[0], NoveltyBaseline):
        judged = judge_record(models[0].model, models[0].reference, x, y, alpha=settings.alpha)
        return Evaluation(versions, model_set(versions), novelty_result(judged), judged)
    baseline = models[0] if isinstance(models[0], PooledModel) and not models[0].is_fault_mode else None
    if channels:
        vectors = [model for model in models if isinstance(model, VectorFNARX)]
        xa, ya, names = vector_record(active, x, y, channels, settings.lags)
        inspection = inspect_vector(xa, ya, vectors, alpha=settings.alpha, lags=settings.lags)
        result = vector_verdict(inspection, vectors, names, settings.alpha, settings.lags, len(xa))
    elif isinstance(models[0], FreeRunMode):
        result = inspect_free_run(x, y, models, alpha=settings.alpha)  # type: ignore[arg-type]
    elif baseline is not None:
        check = check_baseline(baseline, x, y, conditions, alpha=settings.alpha, lags=settings.lags)
        result = baseline_verdict(check, len(x))
    else:
        result = inspect(x, y, at_conditions(active, conditions), alpha=settings.alpha, lags=settings.lags)
    return Evaluation(versions, model_set(versions), result)


def novelty_result(judged: NoveltyVerdict) -> InspectionVerdict:
    """A healthy baseline's judgement as a verdict: ``healthy`` or ``anomaly`` (a record unlike
    the healthy ones that no fault mode describes, so no magnitude), detected by ``novelty``, the
    test of its free-run error; no fault mode, no magnitude or Ljung–Box test."""
    anomaly = judged.status == "anomaly"
    return InspectionVerdict(
        status=judged.status,
        fault_detected=anomaly,
        fault_mode=None,
        reference_mode=None,
        k_hat=None,
        sigma_k=None,
        interval=None,
        alpha=judged.alpha,
        lags=None,
        n_samples=judged.n_samples,
        z_critical=None,
        q_critical_detection=None,
        detected_by=("novelty",) if anomaly else (),
        modes=(),
    )


def vector_record(
    active: Active, x: ArrayLike, y: ArrayLike, channels: Sequence[str], lags: int
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """x and y of a record of several ``channels``, y's columns put in the order of the active
    vector models' channels (which are returned), after checking that the record has exactly their
    channels (naming those missing and those beyond) and that it is long enough and finite."""
    names: list[str] | None = None
    for version, _ in active:
        model_channels = version.training["channels"]
        order = channel_rules.matched(channels, model_channels, version.name)
        if names is not None and model_channels != names:
            raise InputError(
                f"the active vector models order their channels differently ({', '.join(names)} and "
                f"{', '.join(model_channels)}); train them from records of one channel order"
            )
        names = model_channels
    assert names is not None  # models_to_inspect_with gives at least one
    longest = max(model.lags for _, model in active if isinstance(model, VectorFNARX))
    xa, ya = checked_signals(x, y, channels, minimum_samples(lags, longest), degree=1)
    return xa, ya[:, order], names


def checked_to_queue(
    active: Active, x: ArrayLike, y: ArrayLike, conditions: Mapping[str, float], lags: int
) -> tuple[np.ndarray, np.ndarray]:
    """A record of one response checked as its queued inspection under the ``active`` models at
    its ``conditions`` will check it: by the chain's rules, or a healthy baseline's alone."""
    baseline = active[0][1]
    if isinstance(baseline, NoveltyBaseline):
        return checked_for_judgement(baseline.model, baseline.reference, x, y)
    if isinstance(baseline, FreeRunMode):
        return checked_for_free_run(x, y, [model for _, model in active])  # type: ignore[misc]
    return checked_for_inspection(x, y, at_conditions(active, conditions), lags)


def at_conditions(active: Active, conditions: Mapping[str, float]) -> list[FNARX | NARX]:
    """The models as they stand at a record's ``conditions``: each pooled one evaluated there,
    which refuses a record without a variable it needs or outside the range it was trained on;
    the others as they are."""
    return [_at(model, conditions) for _, model in active]


def _at(model: FNARX | PooledModel, conditions: Mapping[str, float]) -> FNARX | NARX:
    if not isinstance(model, PooledModel):
        return model
    return model.fnarx_at(conditions) if model.is_fault_mode else model.narx_at(conditions)


def model_set(versions: list[ModelVersion]) -> str:
    """The key a verdict is stored under: the ids of the model versions that gave it."""
    return ",".join(str(v.id) for v in sorted(versions, key=lambda v: v.id))


def models_to_inspect_with(session: Session, structure: Structure, several: bool = False) -> Active:
    """The structure's active fault-mode models or, when it has none, its active baseline alone if
    that can inspect records (``modelling.active_baseline``); a conflict if it has neither, which
    says why its baseline cannot. For a record of ``several`` channels, its active vector
    fault-mode models, a conflict if it has none; the others are not for such a record, nor the
    vector ones for a record of one response."""
    every = active_fault_modes(session, structure)
    if several:
        vectors = [(version, model) for version, model in every if isinstance(model, VectorFNARX)]
        if not vectors:
            raise ConflictError(
                f"structure {structure.name!r} has no active vector fault-mode model for a record of several "
                f"channels: train one with POST /api/v1/structures/{structure.id}/models/vector-fault-modes"
            )
        return vectors
    active = [(version, model) for version, model in every if not isinstance(model, VectorFNARX)]
    if active:
        return _one_chain(structure, active)
    baseline = active_baseline(session, structure)
    if baseline is not None and baseline[1] is not None:
        return [(baseline[0], baseline[1])]
    why = ""
    if baseline is not None:
        reason = (
            baseline[0]
            .statistics.get("novelty", {})
            .get("reason", "it was trained without the reference that judging needs: train it again")
        )
        why = f", and its baseline cannot judge records alone ({reason})"
    raise ConflictError(
        f"structure {structure.name!r} has no active fault-mode model{why}: train one with "
        f"POST /api/v1/structures/{structure.id}/models/fault-modes"
    )


def _one_chain(structure: Structure, active: Active) -> Active:
    """The active fault modes, refused when they mix sensor-noise modes (the free-run chain) with
    the paper's: one chain inspects a record, each with its own statistics, and no verdict can
    compare a mode of one with a mode of the other; and refused when the sensor-noise modes were
    not fitted together, which the free-run chain's localisation assumes."""
    sensor = [version.name for version, model in active if isinstance(model, FreeRunMode)]
    process = [version.name for version, model in active if not isinstance(model, FreeRunMode)]
    if sensor and process:
        raise ConflictError(
            f"structure {structure.name!r} has active fault modes of both noise kinds: "
            f"{', '.join(sensor)} trained with noise 'sensor' (the free-run chain) and {', '.join(process)} "
            "with noise 'process' (the paper's chain), and one inspection uses one chain: train "
            f'{", ".join(process)} again with "noise": "sensor" (or the others with "process") '
            f"at POST /api/v1/structures/{structure.id}/models/fault-modes"
        )
    # One joint fit gives every mode the same healthy error level: different ones mean modes
    # fitted apart (an older version activated), each around its own healthy model.
    levels = {(model.sigma2, model.dof) for _, model in active if isinstance(model, FreeRunMode)}
    if len(levels) > 1:
        raise ConflictError(
            f"the active sensor-noise fault modes of structure {structure.name!r} ({', '.join(sensor)}) were "
            "not fitted together around one healthy model (an older version was activated): train one of "
            f"them again at POST /api/v1/structures/{structure.id}/models/fault-modes, which refits them all"
        )
    return active


def free_run_cells(active: Active, n_samples: int) -> int:
    """What inspecting a record of ``n_samples`` by the free-run chain costs in cells, as a
    training's: its samples times every mode's coefficients (terms × basis functions), whose
    sensitivities a free run carries at each magnitude tried, mode by mode; 0 for the other chains,
    whose cost the record's size bounds."""
    return sum(n_samples * model.model.theta.size for _, model in active if isinstance(model, FreeRunMode))


def check_inspection_cost(active: Active, n_samples: int, settings: Settings, queued: bool) -> None:
    """Refuse a free-run inspection over ``max_training_cells``, or over ``queue_training_cells``
    within a request (not ``queued``): its free runs cost far more a sample than the one-step chain."""
    cells = free_run_cells(active, n_samples)
    what = f"inspecting this record of {n_samples} samples by the free-run chain would cost {cells} cells"
    if cells > settings.max_training_cells:
        raise InputError(
            f"{what}; the limit is {settings.max_training_cells} (NARXWATCH_MAX_TRAINING_CELLS): "
            "send shorter records"
        )
    if not queued and cells > settings.queue_training_cells:
        raise InputError(
            f"{what}, more than a request runs ({settings.queue_training_cells}, "
            "NARXWATCH_QUEUE_TRAINING_CELLS): send the record with inspect=queue, which queues its inspection"
        )


def inspect_stored(session: Session, principal: Principal, record_id: int, settings: Settings) -> Verdict:
    """The caller's stored record inspected (see :func:`inspect_record`) within the request; its
    signals are read only if it has no verdict under the active models yet."""
    unread = [defer(Record.x), defer(Record.y)]
    record = get_owned(session, principal, Record, record_id, "record", options=unread)
    structure = get_structure(session, principal, record.structure_id)
    active = models_to_inspect_with(session, structure, bool(record.channels))
    if _find(session, record.id, model_set([version for version, _ in active])) is None:
        check_inspection_cost(active, record.n_samples, settings, queued=False)
    return inspect_record(session, record, structure, settings, active)


def inspect_record(
    session: Session, record: Record, structure: Structure, settings: Settings, active: Active | None = None
) -> Verdict:
    """The verdict of a stored record under the structure's active fault-mode models (``active``
    when the caller has read them: a job marks a record the models cannot inspect under the same
    model set it inspected it with).

    A verdict the record has under the same models is returned before its signals are read:
    inspecting it again would cost as much as the first time and change nothing. Otherwise
    computed first, then stored: the write transaction (and SQLite's writer gate) begins only
    with the inserts.
    """
    channels = record.channels or ()
    if active is None:
        active = models_to_inspect_with(session, structure, bool(channels))
    existing = _find(session, record.id, model_set([version for version, _ in active]))
    if existing is not None:
        return existing
    evaluation = evaluate(active, settings, *signals(record), condition_values(record.conditions), channels)
    return store_verdict(session, record, structure, evaluation, settings)


def store_verdict(
    session: Session,
    record: Record,
    structure: Structure,
    evaluation: Evaluation,
    settings: Settings,
    new_record: bool = False,
) -> Verdict:
    """Persist an evaluation as the record's verdict, unless one with the same models exists.

    A record already inspected with the same model versions keeps its verdict, so repeating
    an inspection (or a redelivered job) changes nothing. A new verdict has the structure's
    alarm rules run over its history (``service.domain.alarms``). A record stored by this very request
    (``new_record``) cannot have a verdict yet, so none is looked for.
    """
    existing = None if new_record else _find(session, record.id, evaluation.model_set)
    if existing is not None:
        return existing
    result, model_set = evaluation.result, evaluation.model_set
    figures = result.to_dict()  # the inspection's figures by their names, as the verdict row has them
    interval = figures.pop("interval")
    values = {
        "record_id": record.id,
        "structure_id": structure.id,
        "acquired_at": record.acquired_at,
        "model_set": model_set,
        **figures,
        "interval_low": interval[0] if interval else None,
        "interval_high": interval[1] if interval else None,
        "novelty": evaluation.novelty.to_dict() if evaluation.novelty is not None else None,
    }
    inserted = insert_unless_exists(session, Verdict, values, ["record_id", "model_set"])
    if inserted is None:  # the same inspection finished concurrently: keep the first
        found = _find(session, record.id, model_set)
        if found is None:
            raise RuntimeError(f"verdict of record {record.id} conflicted but cannot be found")
        return found
    versions = evaluation.versions
    session.execute(
        insert(VerdictModel.__table__),
        [{"verdict_id": inserted.id, "model_version_id": v.id} for v in versions],
    )
    stored = alarms.point(
        inserted.id,
        record.id,
        record.acquired_at,
        result.status,
        result.reference_mode,
        values["interval_low"],
        values["interval_high"],
        values["modes"],
    )
    # In the same transaction: the verdict and its alarms (and the rules' kept state), or neither.
    limit = acquisition_limit(settings)
    alarms.evaluate(session, structure, limit, stored, new_record)
    # Counted last: the state row, which every upload of the structure updates, is then locked
    # only until the commit, not through the alarms' evaluation (alarms.lock: the lock order).
    fleet.count_verdict(
        session,
        inserted.id,
        structure.id,
        record.acquired_at,
        result.status,
        limit,
    )
    return Verdict(
        id=inserted.id,
        created_at=inserted.created_at,
        models=versions,
        conditions=record.conditions,
        **values,
    )


def verdict_under(session: Session, record_id: int, versions: list[ModelVersion]) -> Verdict | None:
    """The record's verdict under exactly these model versions, if it has one."""
    return _find(session, record_id, model_set(versions))


def get_verdict(session: Session, principal: Principal, verdict_id: int) -> Verdict:
    return get_owned(session, principal, Verdict, verdict_id, "verdict", options=[MODEL_REFS, CONDITIONS])


def _find(session: Session, record_id: int, model_set: str) -> Verdict | None:
    query = (
        select(Verdict)
        .where(Verdict.record_id == record_id, Verdict.model_set == model_set)
        .options(MODEL_REFS, CONDITIONS)
    )
    return session.scalar(query)
