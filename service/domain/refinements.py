"""Refinements: the loop of SPEC §7 run on stored records from a baseline version (or, with none,
from the linear orders it chooses), kept with its report."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session, selectinload

from models.assessment import check_test_length
from models.effects import candidate_effects, linear_terms
from models.errors import InputError
from models.narx import NARX
from models.refinement import MAX_LINEAR_ORDER, check_parts, reach
from models.refinement_protocol import Loop, Refined, default_split, refine_parts, refine_whole
from models.terms import Term
from service.config import Settings
from service.domain.errors import NotFoundError
from service.domain.modelling import (
    BASELINE,
    bounded_document,
    check_cost,
    check_one_response,
    new_version,
    owned_records,
)
from service.domain.records import signals
from service.domain.structures import get_owned, get_structure, list_owned
from service.schemas import RefinementCreate
from service.security import Principal
from service.tables import ModelVersion, Record, Refinement, RefinementRecord, Structure

# A refinement's model versions as its answer names them (id, name, version), never their
# documents, and the records it was fitted and judged on.
REFINEMENT_PARTS = [
    selectinload(relation).load_only(ModelVersion.id, ModelVersion.name, ModelVersion.version)
    for relation in (Refinement.base_model, Refinement.refined_model)
] + [selectinload(Refinement.records)]


@dataclass(frozen=True)
class _Plan:
    """A refinement checked and priced: its records' signals not yet read.

    On one record, ``estimation`` and ``test`` are its parts; on several, ``tests`` holds the
    records judged whole and ``estimation``/``test`` are None."""

    structure: Structure
    records: list[Record]
    tests: list[Record]
    base: ModelVersion | None
    terms: tuple[Term, ...] | None  # None: the loop chooses a linear model's orders
    estimation: list[tuple[int, int]] | None
    test: tuple[int, int] | None
    cells: int


def create_refinement(
    session: Session,
    principal: Principal,
    structure_id: int,
    body: RefinementCreate,
    settings: Settings,
    job: str | None = None,
) -> Refinement:
    """Refine, then store the report and, if an effect was added, the refined model as a new
    inactive version of the base model's name (with no base, the refined model always: the
    linear model chosen, or what the loop added to it, as a new inactive baseline). A queued
    refinement's report is marked with its ``job`` token (see :func:`refinement_of_job`).

    The loop runs before the first write, so the write lock is held only for the inserts.
    """
    plan = _planned(session, principal, structure_id, body, settings)
    refined, judged, data = _refined(plan, body)
    document = refined.to_dict(judged)  # what each effect does, on the first record judged
    document["data"] = (
        {
            "record_ids": [r.id for r in plan.records],
            "test_record_ids": [r.id for r in plan.tests],
        }
        | data
        | {"initial": body.initial, "alpha": body.alpha}
        | ({"job": job} if job is not None else {})
    )
    stored = None
    if refined.report.refinement.effects_added or plan.base is None:
        stored = _store_refined(session, plan, body, refined, document["orders_chosen"], settings)
    refinement = Refinement(
        structure_id=plan.structure.id,
        record_id=plan.records[0].id,
        base_model=plan.base,
        refined_model=stored,
        report=document,
        records=[
            RefinementRecord(record_id=record.id, role=role, position=position)
            for role, listed in (("estimation", plan.records), ("test", plan.tests))
            for position, record in enumerate(listed)
        ],
    )
    session.add(refinement)
    session.flush()
    return refinement


def _refined(plan: _Plan, body: RefinementCreate) -> tuple[Refined, list[dict[str, Any]], dict[str, Any]]:
    """The loop run as the plan says: the refinement, where each record judged comes from, and
    the protocol as the report's data gives it."""
    # Every record of a structure is stored at its rate.
    loop = Loop(plan.terms, body.initial, body.alpha, plan.structure.fs, body.transient)
    if plan.estimation is not None and plan.test is not None:
        (record,) = plan.records
        x, y = signals(record)
        refined = refine_parts(loop, x, y, plan.estimation, plan.test)
        judged = [{"record_id": record.id, "samples": list(plan.test)}]
        return refined, judged, {"estimation": _as_given(plan.estimation), "test": list(plan.test)}
    # Whole records, fitted through the transient and run from their start (as in `narxwatch
    # refine`); the tests are scored after it.
    cut = body.transient
    fitted = [signals(record) for record in plan.records]
    held = [signals(record) for record in plan.tests]
    names = [f"record {record.id}" for record in plan.records]
    refined = refine_whole(loop, fitted, held, names)
    judged = [{"record_id": r.id, "samples": [cut, r.n_samples]} for r in plan.tests]
    return refined, judged, {"transient": cut}


def _store_refined(
    session: Session,
    plan: _Plan,
    body: RefinementCreate,
    refined: Refined,
    orders_chosen: list[int] | None,
    settings: Settings,
) -> ModelVersion:
    """The refined model, stored as a new inactive version of the base model's name (with no
    base, a new baseline), with how it was trained."""
    base, result = plan.base, refined.report.refinement
    model = result.refined
    training = {
        "refined_from": base.id if base is not None else None,
        "orders_chosen": orders_chosen,
        "record_ids": [r.id for r in plan.records],
        **(
            {"estimation": _as_given(plan.estimation)}
            if plan.estimation is not None
            else {"transient": body.transient}
        ),
        # The samples left out at each estimation part's start, where the system had not yet
        # settled: the model was fitted on the rest (empty where nothing was left out).
        "settled_from": list(result.settled_from),
        "effects_added": [effect.name for effect in result.effects_added],
        "terms": model.term_names,
        "estimator": result.estimator,
        # The moving-average noise model, if one was added: the stored model is its
        # process part, which the inspection chain and free runs use.
        "noise_ma": result.noise.tolist(),
    }
    statistics = {"sigma2": model.sigma2, "n_obs": model.n_obs}
    return new_version(
        session,
        plan.structure,
        "baseline",
        base.name if base is not None else BASELINE,
        bounded_document(model.to_document(), settings),
        training,
        statistics,
        active=False,
    )


def refinement_of_job(session: Session, structure_id: int, record_id: int, token: str) -> Refinement | None:
    """The refinement a queued job (marked ``report["data"]["job"]``) has stored already, if any;
    ``record_id`` is the first record it fits."""
    query = select(Refinement).where(
        Refinement.structure_id == structure_id, Refinement.record_id == record_id
    )
    return next((r for r in session.scalars(query) if r.report["data"].get("job") == token), None)


def refinement_cells(
    session: Session, principal: Principal, structure_id: int, body: RefinementCreate, settings: Settings
) -> int:
    """What a refinement costs in cells (the samples of every record it reads × the base model's
    terms and the candidate regressors offered), from the records' lengths alone: it decides
    whether the refinement runs at once or as a job. Refuses one over the limits."""
    return _planned(session, principal, structure_id, body, settings).cells


def _planned(
    session: Session, principal: Principal, structure_id: int, body: RefinementCreate, settings: Settings
) -> _Plan:
    """What can be checked without the signals is, so that a queued refinement fails for no
    reason its request could have given."""
    structure = get_structure(session, principal, structure_id)
    fitted_ids, test_ids = body.estimation_record_ids, body.test_record_ids or []
    both = set(fitted_ids) & set(test_ids)
    if both:
        raise InputError(
            f"record {min(both)} is listed to fit and to judge; judge the models on records not fitted"
        )
    records = owned_records(session, principal, structure, fitted_ids + test_ids)
    check_one_response(records, structure, "a refinement")
    fitted, tests = records[: len(fitted_ids)], records[len(fitted_ids) :]
    base = None if body.base_model_id is None else _base(session, structure, body.base_model_id)
    terms = None if base is None else NARX.from_document(base.document).terms
    estimation = test = None
    if body.record_id is not None:
        n = fitted[0].n_samples
        default_estimation, default_test = default_split(n)
        estimation = body.estimation_parts or [default_estimation]
        test = (body.test[0], body.test[1]) if body.test else default_test
        check_parts(n, terms, estimation, test, body.initial)
    else:
        for record in records:
            if record.n_samples <= body.transient:
                raise InputError(
                    f"record {record.id} has {record.n_samples} samples; a transient of "
                    f"{body.transient} leaves nothing of it"
                )
        start_up = max(body.initial, reach(terms), body.transient)
        for record in tests:
            try:
                check_test_length(record.n_samples, start_up)
            except InputError as exc:
                raise InputError(f"test record {record.id}: {exc}") from None
    # With no base, priced as the largest linear model the loop may choose.
    start = terms or linear_terms(MAX_LINEAR_ORDER, MAX_LINEAR_ORDER, 0)
    regressors = len(start) + sum(effect.regressors for effect in candidate_effects(start))
    cells = sum(record.n_samples for record in records) * regressors
    check_cost(cells, regressors, settings, "this refinement")
    return _Plan(structure, fitted, tests, base, terms, estimation, test, cells)


def _as_given(parts: list[tuple[int, int]]) -> list[int] | list[list[int]]:
    """Estimation parts as a request gives them: one as [a, b], several as [[a, b], [c, d], …]."""
    return list(parts[0]) if len(parts) == 1 else [list(part) for part in parts]


def _base(session: Session, structure: Structure, model_id: int) -> ModelVersion:
    """The baseline NARX version a refinement starts from, refused if it is anything else."""
    base = session.get(ModelVersion, model_id)
    if base is None or base.structure_id != structure.id:
        raise NotFoundError("model version", model_id)
    if base.kind != "baseline":
        raise InputError(
            f"model version {base.id} is a {base.kind.replace('_', '-')} model; refinement starts from a "
            "baseline NARX version"
        )
    if base.document.get("kind") == "pooled":
        raise InputError(
            f"model version {base.id} is a pooled baseline; refinement starts from a baseline NARX "
            "identified at one condition"
        )
    return base


def list_refinements(session: Session, principal: Principal, structure_id: int) -> list[Refinement]:
    """The structure's refinements, newest first."""
    return list_owned(session, principal, Refinement, structure_id, [Refinement.id.desc()], REFINEMENT_PARTS)


def get_refinement(session: Session, principal: Principal, refinement_id: int) -> Refinement:
    return get_owned(session, principal, Refinement, refinement_id, "refinement", options=REFINEMENT_PARTS)
