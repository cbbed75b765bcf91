"""Structures (monitored assets), always seen through the caller's organisation."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, TypeVar

from sqlalchemy import exists, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from recordfiles.quantities import SignalDeclaration, signal_label
from service.domain import fleet
from service.domain.errors import ConflictError, NotFoundError
from service.schemas import Signal, StructureCreate, StructureUpdate
from service.security import Principal
from service.tables import ModelVersion, Record, Structure

# The signals a structure declares, each with its symbol in labels.
SIGNALS = {"excitation": "x", "response": "y"}


def create_structure(session: Session, principal: Principal, body: StructureCreate) -> Structure:
    structure = Structure(
        organisation_id=principal.organisation_id, name=body.name, fs=body.fs, description=body.description
    )
    for signal in SIGNALS:
        _declare(structure, signal, getattr(body, signal))
    session.add(structure)
    _flush_name(session, structure)
    fleet.open_state(session, structure)
    return structure


def update_structure(
    session: Session, principal: Principal, structure_id: int, body: StructureUpdate
) -> Structure:
    """Change what ``body`` sends of a structure's name, description and declarations.

    A declaration says what the numbers of the structure's records are, and so what its models'
    coefficients are in: once it has records or models, a declaration may be completed (stated
    where there was none, or its unit where none was stated) but not changed or withdrawn, which
    would relabel data measured otherwise. The request fails whole if any part is refused."""
    structure = get_structure(session, principal, structure_id)
    named = structure.name
    sent = body.model_dump(exclude_unset=True)
    contradicted = [
        signal
        for signal in SIGNALS
        if signal in sent and not _completes(getattr(structure, signal), getattr(body, signal))
    ]
    for name in ("name", "description"):
        if name in sent:
            setattr(structure, name, sent[name])
    declared = {signal: getattr(structure, signal) for signal in contradicted}
    for signal in SIGNALS:
        if signal in sent:
            _declare(structure, signal, getattr(body, signal))
    # The change is written before the records are looked at: SQLite's write lock is then held,
    # and on PostgreSQL the state row's lock waits for uploads under way (each counts its record
    # there), so no record is stored between the look and the commit.
    _flush_name(session, structure)
    if contradicted:
        fleet.lock_states(session, [structure.id])
        held = _held_data(session, structure.id)
        if held:
            signal = contradicted[0]
            was, now = declared[signal], getattr(structure, signal)
            raise ConflictError(
                f"structure {named!r} has {held}: its {signal} is declared as "
                f"{_described(signal, was)} and cannot become {_described(signal, now)}, since its "
                "records and its models' coefficients are in what was declared. A declaration can "
                "only be completed now (stated where none was, or its unit where none was stated); "
                "create another structure for signals measured otherwise"
            )
    return structure


def _declare(structure: Structure, signal: str, declaration: Signal | None) -> None:
    setattr(structure, f"{signal}_quantity", declaration and declaration.quantity)
    setattr(structure, f"{signal}_unit", declaration and declaration.unit)


def _completes(declared: SignalDeclaration | None, sent: Signal | None) -> bool:
    """Whether ``sent`` keeps all that ``declared`` states."""
    if declared is None:
        return True
    return sent is not None and sent.quantity == declared.quantity and declared.unit in (None, sent.unit)


def _described(signal: str, declaration: SignalDeclaration | None) -> str:
    return "nothing" if declaration is None else signal_label(SIGNALS[signal], declaration)


def _held_data(session: Session, structure_id: int) -> str | None:
    """What the structure holds that its declarations describe: "records", "models", both or none."""
    held = [
        what
        for what, table in (("records", Record), ("models", ModelVersion))
        if session.scalar(select(exists().where(table.structure_id == structure_id)))
    ]
    return " and ".join(held) or None


def _flush_name(session: Session, structure: Structure) -> None:
    """Write the structure, refusing a name its organisation gives another already."""
    name = structure.name
    try:
        session.flush()
    except IntegrityError:  # the request fails whole: its session is rolled back
        raise ConflictError(f"a structure named {name!r} already exists in your organisation") from None


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


def list_owned(
    session: Session,
    principal: Principal,
    model: type[Owned],
    structure_id: int,
    order: Sequence[Any],
    options: Sequence[Any] = (),
) -> list[Owned]:
    """The objects of one of the caller's structures in ``order``, loaded with ``options``; another
    organisation's structure is answered as a missing one (:func:`get_structure`)."""
    get_structure(session, principal, structure_id)
    query = select(model).where(model.structure_id == structure_id)
    return list(session.scalars(query.order_by(*order).options(*options)))
