"""Structures (monitored assets), always seen through the caller's organisation."""

from __future__ import annotations

from typing import Any, Protocol, TypeVar

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.domain import fleet
from service.domain.errors import ConflictError, NotFoundError
from service.schemas import StructureCreate
from service.security import Principal
from service.tables import Structure


def create_structure(session: Session, principal: Principal, body: StructureCreate) -> Structure:
    excitation, response = body.excitation, body.response
    structure = Structure(
        organisation_id=principal.organisation_id,
        name=body.name,
        fs=body.fs,
        description=body.description,
        excitation_quantity=excitation and excitation.quantity,
        excitation_unit=excitation and excitation.unit,
        response_quantity=response and response.quantity,
        response_unit=response and response.unit,
    )
    session.add(structure)
    try:
        session.flush()
    except IntegrityError:  # the request fails whole: its session is rolled back
        raise ConflictError(f"a structure named {body.name!r} already exists in your organisation") from None
    fleet.open_state(session, structure)
    return structure


def structure_names(session: Session, principal: Principal, structure_ids: set[int]) -> dict[int, str]:
    """The names of those of ``structure_ids`` that are the caller's structures."""
    query = select(Structure.id, Structure.name).where(
        Structure.organisation_id == principal.organisation_id, Structure.id.in_(structure_ids)
    )
    return {structure_id: name for structure_id, name in session.execute(query)}


def get_structure(session: Session, principal: Principal, structure_id: int) -> Structure:
    structure = session.get(Structure, structure_id)
    if structure is None or structure.organisation_id != principal.organisation_id:
        raise NotFoundError("structure", structure_id)
    return structure


class _OfStructure(Protocol):
    structure_id: int


Owned = TypeVar("Owned", bound=_OfStructure)


def get_owned(
    session: Session, principal: Principal, model: type[Owned], object_id: int, label: str, **options: Any
) -> Owned:
    """An object of one of the caller's structures. Another organisation's is answered exactly
    as a missing one, so that ids reveal nothing across organisations."""
    found = session.get(model, object_id, **options)
    if found is None:
        raise NotFoundError(label, object_id)
    try:
        get_structure(session, principal, found.structure_id)
    except NotFoundError:
        raise NotFoundError(label, object_id) from None
    return found
