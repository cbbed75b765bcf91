"""Where each structure stands: its latest verdict, since when that status holds, and counts."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

from sqlalchemy import and_, func, or_, select
from sqlalchemy.orm import Session

from service.domain.inspections import MODEL_REFS
from service.domain.structures import list_structures
from service.security import Principal
from service.tables import Structure, Verdict

STATUSES = ("healthy", "faulty", "unknown_fault")


@dataclass(frozen=True)
class StructureStatus:
    """``since`` is when the current run of ``latest.status`` began: the acquisition time of the
    first verdict after the last one with another status (of the first verdict, if none)."""

    structure: Structure
    latest: Verdict | None
    since: dt.datetime | None
    counts: dict[str, int]


def fleet(session: Session, principal: Principal) -> list[StructureStatus]:
    """Every structure of the caller's organisation with where it stands."""
    structures = list_structures(session, principal)
    counts = _counts(session, [s.id for s in structures])
    return [_status(session, s, counts.get(s.id, {})) for s in structures]


def structure_status(session: Session, structure: Structure) -> StructureStatus:
    return _status(session, structure, _counts(session, [structure.id]).get(structure.id, {}))


def _status(session: Session, structure: Structure, counts: dict[str, int]) -> StructureStatus:
    latest = session.scalar(
        select(Verdict)
        .where(Verdict.structure_id == structure.id)
        .order_by(Verdict.acquired_at.desc(), Verdict.id.desc())
        .limit(1)
        .options(MODEL_REFS)
    )
    since = _since(session, latest) if latest is not None else None
    return StructureStatus(structure, latest, since, {s: counts.get(s, 0) for s in STATUSES})


def _since(session: Session, latest: Verdict) -> dt.datetime | None:
    of_structure = Verdict.structure_id == latest.structure_id
    other = session.execute(
        select(Verdict.acquired_at, Verdict.id)
        .where(of_structure, Verdict.status != latest.status)
        .order_by(Verdict.acquired_at.desc(), Verdict.id.desc())
        .limit(1)
    ).first()
    query = select(func.min(Verdict.acquired_at)).where(of_structure)
    if other is not None:
        at, verdict_id = other
        query = query.where(
            or_(Verdict.acquired_at > at, and_(Verdict.acquired_at == at, Verdict.id > verdict_id))
        )
    return session.scalar(query)


def _counts(session: Session, structure_ids: list[int]) -> dict[int, dict[str, int]]:
    counts: dict[int, dict[str, int]] = {}
    if not structure_ids:
        return counts
    rows = session.execute(
        select(Verdict.structure_id, Verdict.status, func.count())
        .where(Verdict.structure_id.in_(structure_ids))
        .group_by(Verdict.structure_id, Verdict.status)
    )
    for structure_id, status, count in rows:
        counts.setdefault(structure_id, {})[status] = count
    return counts
