"""Refinements: the loop of SPEC §7 run on a stored record from a baseline version, kept with its report."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session, defer, selectinload

from models.effects import candidate_effects
from models.errors import InputError
from models.narx import NARX
from models.refinement import check_parts, refine_record
from models.terms import Term
from service.config import Settings
from service.domain.errors import NotFoundError
from service.domain.modelling import bounded_document, check_cost, new_version
from service.domain.records import signals
from service.domain.structures import get_owned, get_structure
from service.schemas import RefinementCreate
from service.security import Principal
from service.tables import ModelVersion, Record, Refinement, Structure

# A refinement's model versions as its answer names them (id, name, version), never their documents.
MODEL_REFS = [
    selectinload(relation).load_only(ModelVersion.id, ModelVersion.name, ModelVersion.version)
    for relation in (Refinement.base_model, Refinement.refined_model)
]


@dataclass(frozen=True)
class _Plan:
    """A refinement checked and priced: its record's signals not yet read."""

    structure: Structure
    record: Record
    base: ModelVersion
    terms: tuple[Term, ...]
    estimation: tuple[int, int]
    test: tuple[int, int]
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
    inactive version of the base model's name. A queued refinement's report is marked
    with its ``job`` token (see :func:`refinement_of_job`).

    The loop runs before the first write, so the write lock is held only for the inserts.
    """
    plan = _planned(session, principal, structure_id, body, settings)
    structure, record, base = plan.structure, plan.record, plan.base
    estimation, test = plan.estimation, plan.test
    x, y = signals(record)
    report = refine_record(x, y, plan.terms, estimation, test, body.initial, body.alpha, record.fs)
    document = report.to_dict() | {
        "data": {
            "estimation": list(estimation),
            "test": list(test),
            "initial": body.initial,
            "alpha": body.alpha,
        }
        | ({"job": job} if job is not None else {})
    }
    refined = None
    if report.refinement.effects_added:
        model = report.refinement.refined
        training = {
            "refined_from": base.id,
            "record_ids": [record.id],
            "estimation": list(estimation),
            "effects_added": [effect.name for effect in report.refinement.effects_added],
            "terms": model.term_names,
            # The moving-average noise model, if one was added: the stored model is its
            # process part, which the inspection chain and free runs use.
            "noise_ma": report.refinement.noise.tolist(),
        }
        statistics = {"sigma2": model.sigma2, "n_obs": model.n_obs}
        refined = new_version(
            session,
            structure,
            base.kind,
            base.name,
            bounded_document(model.to_document(), settings),
            training,
            statistics,
            active=False,
        )
    refinement = Refinement(
        structure_id=structure.id,
        record_id=record.id,
        base_model=base,
        refined_model=refined,
        report=document,
    )
    session.add(refinement)
    session.flush()
    return refinement


def refinement_of_job(session: Session, structure_id: int, record_id: int, token: str) -> Refinement | None:
    """The refinement a queued job (marked ``report["data"]["job"]``) has stored already, if any."""
    query = select(Refinement).where(
        Refinement.structure_id == structure_id, Refinement.record_id == record_id
    )
    return next((r for r in session.scalars(query) if r.report["data"].get("job") == token), None)


def refinement_cells(
    session: Session, principal: Principal, structure_id: int, body: RefinementCreate, settings: Settings
) -> int:
    """What a refinement costs in cells (the record's samples × the base model's terms and the
    candidate regressors offered), from the record's length alone: it decides whether the
    refinement runs at once or as a job. Refuses one over the limits."""
    return _planned(session, principal, structure_id, body, settings).cells


def _planned(
    session: Session, principal: Principal, structure_id: int, body: RefinementCreate, settings: Settings
) -> _Plan:
    structure = get_structure(session, principal, structure_id)
    unread = [defer(Record.x), defer(Record.y)]
    record = get_owned(session, principal, Record, body.record_id, "record", options=unread)
    if record.structure_id != structure.id:
        raise InputError(f"record {record.id} belongs to another structure, not {structure.name!r}")
    base = session.get(ModelVersion, body.base_model_id)
    if base is None or base.structure_id != structure.id:
        raise NotFoundError("model version", body.base_model_id)
    if base.kind != "baseline":
        raise InputError(
            f"model version {base.id} is a {base.kind.replace('_', '-')} model; refinement starts from a "
            "baseline NARX version"
        )
    terms = NARX.from_document(base.document).terms
    n = record.n_samples
    estimation = (body.estimation[0], body.estimation[1]) if body.estimation else (0, 2 * n // 3)
    test = (body.test[0], body.test[1]) if body.test else (2 * n // 3, n)
    check_parts(n, terms, estimation, test, body.initial)
    regressors = len(terms) + sum(len(effect.terms) for effect in candidate_effects(terms))
    cells = n * regressors
    check_cost(cells, regressors, settings, "this refinement")
    return _Plan(structure, record, base, terms, estimation, test, cells)


def list_refinements(session: Session, principal: Principal, structure_id: int) -> list[Refinement]:
    """The structure's refinements, newest first."""
    get_structure(session, principal, structure_id)
    query = select(Refinement).where(Refinement.structure_id == structure_id).order_by(Refinement.id.desc())
    return list(session.scalars(query.options(*MODEL_REFS)))


def get_refinement(session: Session, principal: Principal, refinement_id: int) -> Refinement:
    return get_owned(session, principal, Refinement, refinement_id, "refinement", options=MODEL_REFS)
