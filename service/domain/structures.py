"""Structures (monitored assets), always seen through the caller's organisation."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.domain.errors import ConflictError, NotFoundError
from service.schemas import StructureCreate
from service.security import Principal
from service.tables import Structure


def create_structure(session: Session, principal: Principal, body: StructureCreate) -> Structure:
    structure = Structure(
        organisation_id=principal.organisation_id, name=body.name, fs=body.fs, description=body.description
    )
    session.add(structure)
    try:
        session.flush()
    except IntegrityError:  # the request fails whole: its session is rolled back
        raise ConflictError(f"a structure named {body.name!r} already exists in your organisation") from None
    return structure


def list_structures(session: Session, principal: Principal) -> list[Structure]:
    query = select(Structure).where(Structure.organisation_id == principal.organisation_id)
    return list(session.scalars(query.order_by(Structure.id)))


def get_structure(session: Session, principal: Principal, structure_id: int) -> Structure:
    structure = session.get(Structure, structure_id)
    if structure is None or structure.organisation_id != principal.organisation_id:
        raise NotFoundError("structure", structure_id)
    return structure
