"""Refinements: the loop of SPEC §7 run on a stored record from a baseline version, kept with its report."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from models.errors import InputError
from models.narx import NARX
from models.refinement import refine_record
from service.domain.errors import NotFoundError
from service.domain.modelling import new_version
from service.domain.records import get_record, signals
from service.domain.structures import get_owned, get_structure
from service.schemas import RefinementCreate
from service.security import Principal
from service.tables import ModelVersion, Refinement


def create_refinement(
    session: Session, principal: Principal, structure_id: int, body: RefinementCreate
) -> Refinement:
    """Refine, then store the report and, if an effect was added, the refined model as a new
    inactive version of the base model's name.

    The loop runs before the first write, so the write lock is held only for the inserts.
    """
    structure = get_structure(session, principal, structure_id)
    record = get_record(session, principal, body.record_id)
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
    x, y = signals(record)
    n = len(x)
    estimation = (body.estimation[0], body.estimation[1]) if body.estimation else (0, 2 * n // 3)
    test = (body.test[0], body.test[1]) if body.test else (2 * n // 3, n)
    report = refine_record(
        x, y, NARX.from_document(base.document).terms, estimation, test, body.initial, body.alpha, record.fs
    )
    document = report.to_dict() | {
        "data": {
            "estimation": list(estimation),
            "test": list(test),
            "initial": body.initial,
            "alpha": body.alpha,
        }
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
            model.to_document(),
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


def list_refinements(session: Session, principal: Principal, structure_id: int) -> list[Refinement]:
    """The structure's refinements, newest first."""
    get_structure(session, principal, structure_id)
    query = select(Refinement).where(Refinement.structure_id == structure_id).order_by(Refinement.id.desc())
    return list(session.scalars(query))


def get_refinement(session: Session, principal: Principal, refinement_id: int) -> Refinement:
    return get_owned(session, principal, Refinement, refinement_id, "refinement")
