"""Where each structure stands, kept on write; the fleet listed a page at a time.

Each structure has one ``StructureState`` row: its latest verdict, since when that status holds,
and how many records and verdicts it has. Every write that changes one of these updates the row
in its own transaction (:func:`count_record`, :func:`count_verdict`; the retention's deletions
through :func:`uncount_verdicts` and :func:`uncount_records`), so the fleet views, the summary and
``/metrics`` read a row per structure, never the structure's history.
"""

from __future__ import annotations

import base64
import binascii
import datetime as dt
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, get_args

from sqlalchemy import Row, and_, bindparam, func, or_, select, update
from sqlalchemy.orm import Session, joinedload

from models.errors import InputError
from models.inspection import Status
from service.domain.paging import Page
from service.schemas import MAX_ID
from service.security import Principal
from service.tables import Structure, StructureState, Verdict

STATUSES: tuple[Status, ...] = get_args(Status)
# A structure's standing as the fleet filter names it: a verdict's status, or none yet.
Standing = Literal[Status, "uninspected"]
STANDINGS: tuple[Standing, ...] = get_args(Standing)
PAGE_SIZE, MAX_PAGE_SIZE = 100, 1000  # structures per page: by default, and at most
# What a row of a fleet page shows of the latest verdict: not its documents (the fault modes' figures),
# whose reading and decoding took most of a page's time.
LISTED = joinedload(StructureState.latest).load_only(
    Verdict.status,
    Verdict.acquired_at,
    Verdict.fault_mode,
    Verdict.k_hat,
    Verdict.interval_low,
    Verdict.interval_high,
)


# The statements of every upload, built once (their compiled forms are cached by SQLAlchemy;
# building the expressions anew cost more than running them), on the table rather than the mapped
# class: an ORM-enabled update runs the session's bulk-update machinery, several times a Core one.
STATES = StructureState.__table__
OF_STRUCTURE = STATES.c.structure_id == bindparam("structure")
COUNT_RECORD = update(STATES).where(OF_STRUCTURE).values(records=STATES.c.records + 1)
LOCK_STATE = (
    select(STATES.c.status, STATES.c.since, STATES.c.latest_verdict_id, STATES.c.latest_acquired_at)
    .where(OF_STRUCTURE)
    .with_for_update()
)
# A verdict newer than the latest, by status: its count up by one, and it the latest.
COUNT_NEWEST = {
    status: update(STATES)
    .where(OF_STRUCTURE)
    .values(
        {
            status: STATES.c[status] + 1,
            "status": status,
            "since": bindparam("since"),
            "latest_verdict_id": bindparam("verdict"),
            "latest_acquired_at": bindparam("acquired_at"),
        }
    )
    for status in STATUSES
}


@dataclass(frozen=True)
class StructureStatus:
    """``since`` is when the current run of ``latest.status`` began: the acquisition time of the
    first verdict after the last one with another status (of the first verdict, if none)."""

    structure: Structure
    latest: Verdict | None
    since: dt.datetime | None
    counts: dict[str, int]

    @property
    def status(self) -> str | None:
        """The latest verdict's status; None before the structure's first verdict."""
        return self.latest.status if self.latest is not None else None


def open_state(session: Session, structure: Structure) -> None:
    """The state row of a structure just created (flushed), in the same transaction."""
    session.add(StructureState(structure_id=structure.id, organisation_id=structure.organisation_id))


def count_record(session: Session, structure_id: int) -> None:
    """One more record stored for the structure. An increment in the database (``records + 1``),
    so concurrent uploads never lose one: each waits for the other's row lock, then adds to its
    committed value."""
    counted = session.execute(COUNT_RECORD, {"structure": structure_id})
    if counted.rowcount != 1:
        raise RuntimeError(f"structure {structure_id} has no state row: run `narxwatch db upgrade`")


def count_verdict(
    session: Session,
    verdict_id: int,
    structure_id: int,
    acquired_at: dt.datetime,
    status: Status,
    limit: dt.datetime,
) -> None:
    """A verdict just inserted, added to its structure's state.

    The row is locked first (``FOR UPDATE``; SQLite's write lock is held already), so the
    verdicts of one structure are applied one after another, each seeing those committed before.
    A verdict newer than the latest (by acquisition time, then id) becomes the latest; its run
    goes on if its status is the same, else starts with it. An older one (a record uploaded late)
    leaves the latest alone but may shorten or lengthen the current run, which is then read again
    from the history: rare, and an indexed range of one structure's verdicts.

    A verdict acquired after ``limit`` (``records.acquisition_limit``: the server's clock plus the
    skew allowed) is counted but never becomes the latest, nor part of the run: it is a record
    stored before uploads' acquisition times were checked, or under a larger skew, and the
    structure's standing is what was acquired up to now. A record dated 9999 would otherwise be
    the latest for ever, every fault acquired after it reading as the status it had. So the
    verdicts past the latest are exactly those that were in the future when counted, and the
    run is read from the verdicts up to the latest alone. A latest itself past ``limit`` (the
    state of a database written before, or the skew since lowered) is read again from the
    history up to ``limit``.
    """
    state = session.execute(LOCK_STATE, {"structure": structure_id}).one_or_none()
    if state is None:
        raise RuntimeError(f"structure {structure_id} has no state row: run `narxwatch db upgrade`")
    newer = state.latest_verdict_id is None or (acquired_at, verdict_id) > (
        state.latest_acquired_at,
        state.latest_verdict_id,
    )
    values: dict[str, Any]
    if state.latest_acquired_at is not None and state.latest_acquired_at > limit:
        values = _newest(session, structure_id, limit)
    elif acquired_at > limit:
        values = {}
    elif newer:
        since = state.since if status == state.status else acquired_at
        session.execute(
            COUNT_NEWEST[status],
            {"structure": structure_id, "since": since, "verdict": verdict_id, "acquired_at": acquired_at},
        )
        return
    else:
        values = dict(since=_since(session, structure_id, state.status, state.latest_acquired_at))
    session.execute(
        update(StructureState)
        .where(StructureState.structure_id == structure_id)
        .values({status: getattr(StructureState, status) + 1, **values})
    )


@dataclass(frozen=True)
class Removed:
    """A verdict deleted (by the retention), as its ``DELETE … RETURNING`` gave it."""

    id: int
    structure_id: int
    status: Status
    acquired_at: dt.datetime


def lock_states(session: Session, structure_ids: Iterable[int]) -> dict[int, Row[Any]]:
    """Lock the state rows of these structures before deleting from them, in order of id, so two
    deleters never wait for each other; each row's latest verdict and since-when as they stand.
    Taken before the deletion, which sets ``latest_verdict_id`` to NULL if it removes the latest."""
    rows = session.execute(
        select(
            StructureState.structure_id,
            StructureState.status,
            StructureState.latest_verdict_id,
            StructureState.latest_acquired_at,
            StructureState.since,
        )
        .where(StructureState.structure_id.in_(sorted(set(structure_ids))))
        .order_by(StructureState.structure_id)
        .with_for_update()
    )
    return {row.structure_id: row for row in rows}


def uncount_verdicts(session: Session, locked: dict[int, Row[Any]], removed: Sequence[Removed]) -> None:
    """Verdicts just deleted, taken off their structures' states (locked by :func:`lock_states`).

    Each status count goes down by as many as were deleted. If the latest verdict went, the
    newest left up to its acquisition time becomes the latest (none: the structure is uninspected
    again); if verdicts of the current run went, the run is read again from the history, which
    now starts later. Neither reads past the latest: the verdicts there were in the future when
    counted (:func:`count_verdict`), and the retention, which deletes the oldest, must not make
    one of them the latest."""
    by_structure: dict[int, list[Removed]] = {}
    for verdict in removed:
        by_structure.setdefault(verdict.structure_id, []).append(verdict)
    for structure_id, gone in by_structure.items():
        state = locked[structure_id]
        values: dict[str, Any] = {
            status: getattr(StructureState, status) - n
            for status, n in Counter(v.status for v in gone).items()
        }
        if state.latest_verdict_id in {v.id for v in gone}:
            values |= _newest(session, structure_id, state.latest_acquired_at)
        elif state.since is not None and max(v.acquired_at for v in gone) >= state.since:
            values["since"] = _since(session, structure_id, state.status, state.latest_acquired_at)
        session.execute(
            update(StructureState).where(StructureState.structure_id == structure_id).values(**values)
        )


def uncount_records(session: Session, structure_ids: Sequence[int]) -> None:
    """Records just deleted (one structure id per record), taken off their structures' states."""
    for structure_id, n in Counter(structure_ids).items():
        session.execute(
            update(StructureState)
            .where(StructureState.structure_id == structure_id)
            .values(records=StructureState.records - n)
        )


def _newest(session: Session, structure_id: int, until: dt.datetime) -> dict[str, Any]:
    """The state's latest-verdict columns read from the structure's verdicts acquired up to ``until``."""
    newest = session.execute(
        select(Verdict.id, Verdict.status, Verdict.acquired_at)
        .where(Verdict.structure_id == structure_id, Verdict.acquired_at <= until)
        .order_by(Verdict.acquired_at.desc(), Verdict.id.desc())
        .limit(1)
    ).first()
    if newest is None:
        return dict(status=None, since=None, latest_verdict_id=None, latest_acquired_at=None)
    return dict(
        status=newest.status,
        since=_since(session, structure_id, newest.status, newest.acquired_at),
        latest_verdict_id=newest.id,
        latest_acquired_at=newest.acquired_at,
    )


def _since(session: Session, structure_id: int, status: str, until: dt.datetime) -> dt.datetime | None:
    """When the run of ``status`` that ends with the latest verdict (acquired at ``until``) began,
    read from the structure's verdicts. Those acquired later are not the structure's yet
    (:func:`count_verdict`): a verdict of another status among them would end the run before it
    began. The first verdict after the last of another status is the latest or earlier, so only
    that last one needs the bound."""
    of_structure = Verdict.structure_id == structure_id
    other = session.execute(
        select(Verdict.acquired_at, Verdict.id)
        .where(of_structure, Verdict.status != status, Verdict.acquired_at <= until)
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


def fleet(
    session: Session,
    principal: Principal,
    *,
    standing: Standing | None = None,
    name: str | None = None,
    cursor: str | None = None,
    limit: int = PAGE_SIZE,
) -> Page[StructureStatus, str]:
    """The caller's structures in order of id, ``limit`` at a time after ``cursor``, optionally
    only those of one ``standing`` and whose name contains ``name`` (any case).

    A page is one range of an index of the state rows (organisation, [status,] id) with each
    row's latest verdict fetched by its id, whatever the length of the history. The name filter
    reads the organisation's structures in order until it has a page: at most all of them.
    """
    if not 1 <= limit <= MAX_PAGE_SIZE:
        raise InputError(f"limit must be between 1 and {MAX_PAGE_SIZE}, not {limit}")
    query = (
        select(StructureState, Structure)
        .join(Structure, Structure.id == StructureState.structure_id)
        .where(StructureState.organisation_id == principal.organisation_id)
    )
    if standing is not None:
        query = query.where(
            StructureState.status.is_(None)
            if standing == "uninspected"
            else StructureState.status == standing
        )
    if name:
        query = query.where(Structure.name.icontains(name, autoescape=True))
    if cursor is not None:
        query = query.where(StructureState.structure_id > _decode(cursor))
    query = query.order_by(StructureState.structure_id).limit(limit + 1).options(LISTED)
    rows = session.execute(query).all()
    page, more = rows[:limit], len(rows) > limit
    return Page(
        items=[_status(structure, state) for state, structure in page],
        next_cursor=_encode(page[-1][1].id) if more else None,
    )


def structure_status(session: Session, structure: Structure) -> StructureStatus:
    state = session.scalar(
        select(StructureState)
        .where(StructureState.structure_id == structure.id)
        .options(joinedload(StructureState.latest))
    )
    if state is None:
        raise RuntimeError(f"structure {structure.id} has no state row: run `narxwatch db upgrade`")
    return _status(structure, state)


def verdict_counts(state: StructureState) -> dict[str, int]:
    return {status: getattr(state, status) for status in STATUSES}


def _status(structure: Structure, state: StructureState) -> StructureStatus:
    return StructureStatus(structure, state.latest, state.since, verdict_counts(state))


def checked_standing(value: str | None) -> Standing | None:
    """A standing from a query string or a form; None for none given."""
    if not value:
        return None
    if value not in STANDINGS:
        raise InputError(f"status must be one of {', '.join(STANDINGS)}, not {value!r}")
    return value  # type: ignore[return-value]


def _encode(structure_id: int) -> str:
    return base64.urlsafe_b64encode(f"structure|{structure_id}".encode()).decode()


def _decode(cursor: str) -> int:
    try:
        kind, structure_id = base64.urlsafe_b64decode(cursor.encode()).decode().split("|")
        if kind != "structure" or not 0 < int(structure_id) <= MAX_ID:
            raise ValueError
        return int(structure_id)
    except (ValueError, binascii.Error, UnicodeDecodeError):
        raise InputError("the cursor is not one this service issued; use the next link of a page") from None
