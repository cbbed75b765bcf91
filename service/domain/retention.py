"""Retention: how long an organisation keeps its records' signals and its verdicts, and the pruning.

A policy gives days of acquisition time (None: forever); an organisation without one keeps the
defaults, signals :data:`DEFAULT_SIGNAL_DAYS` and verdicts :data:`DEFAULT_VERDICT_DAYS`: a
verdict is a few hundred bytes, a record's signals tens of kilobytes, and a verdict keeps its
meaning after the signals are gone.

Pruning goes in four passes, each in batches of at most ``batch`` rows, each batch a short
transaction of its own, so an upload waits at most one batch for the database:

1. signals: the blobs of records acquired before the signal horizon are dropped; the row stays
   (``signals_pruned_at``), with its conditions, for its verdicts;
2. verdicts acquired before the verdict horizon are deleted, and taken off their structures'
   states (counts, latest verdict, since-when) in the same transaction
   (``service.domain.fleet.uncount_verdicts``), so ``/metrics`` and the summary stay exact;
3. records past the verdict horizon, their signals gone and no verdict left, are deleted, and
   taken off the record counts. Records a refinement was fitted or judged on stay: the
   refinement's report refers to them;
4. deliveries (the webhook and e-mail log) written before the verdict horizon are deleted once
   settled, delivered or failed: they announced verdicts of that age. Pending ones never are: the
   outbox still owes them.

A batch takes any rows past the horizon, in no order: a range of an index (``ix_records_signals_kept``,
``ix_verdicts_history``, ``ix_deliveries_settled``) then stops at the batch's size instead of
sorting everything past it.

The job workers' sweep queues one pruning per organisation every ``retention_every_seconds``
(a compare-and-set on ``last_pruned_at``, so however many sweep, each period queues one);
``narxwatch db prune`` runs one at once.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

from sqlalchemy import Select, delete, exists, func, select, update
from sqlalchemy.orm import Session

from service.db import insert_unless_exists
from service.domain import alarms, fleet
from service.domain.schedules import Defer
from service.schemas import Retention
from service.security import Principal
from service.tables import (
    SETTLED,
    Delivery,
    Organisation,
    Record,
    Refinement,
    RefinementRecord,
    RetentionPolicy,
    Structure,
    Verdict,
    utcnow,
)

DEFAULT_SIGNAL_DAYS, DEFAULT_VERDICT_DAYS = 90, 730
BATCH = 1000  # rows a pruning transaction deletes or empties at most
SWEPT = 100  # organisations a sweep queues at most; the next sweep takes the rest
PRUNE = "prune_retention"
KEY = ("organisation_id",)  # what an insert of a policy returns: the table has no id

Pass = Literal["signals", "verdicts", "records", "deliveries"]


@dataclass(frozen=True)
class Policy:
    """An organisation's retention in days (None: forever); ``defaults`` while it keeps the
    service's; ``last_pruned_at`` when its last pruning was queued (None: never)."""

    signal_days: int | None
    verdict_days: int | None
    defaults: bool
    last_pruned_at: dt.datetime | None


@dataclass(frozen=True)
class Batch:
    """One committed batch of a pruning: its pass and how many rows it pruned."""

    organisation_id: int
    what: Pass
    rows: int


@dataclass
class Pruned:
    """What a pruning did: records whose signals it dropped, verdicts, records and deliveries it
    deleted, and the number of transactions it took."""

    signals: int = 0
    verdicts: int = 0
    records: int = 0
    deliveries: int = 0
    batches: int = 0

    def add(self, batch: Batch) -> None:
        setattr(self, batch.what, getattr(self, batch.what) + batch.rows)
        self.batches += 1


def policy(session: Session, organisation_id: int) -> Policy:
    row = session.get(RetentionPolicy, organisation_id)
    if row is None:
        return Policy(DEFAULT_SIGNAL_DAYS, DEFAULT_VERDICT_DAYS, defaults=True, last_pruned_at=None)
    return Policy(row.signal_days, row.verdict_days, row.updated_at is None, row.last_pruned_at)


def set_policy(session: Session, principal: Principal, body: Retention) -> Policy:
    """The caller's organisation's policy set (validated by :class:`service.schemas.Retention`);
    flushes. It applies from the next pruning. The row is made first if missing (as the sweep
    makes it), so two concurrent changes both apply, the later one last, neither failing."""
    organisation_id = principal.organisation_id
    insert_unless_exists(session, RetentionPolicy, _default_row(organisation_id), ["organisation_id"], KEY)
    session.execute(
        update(RetentionPolicy)
        .where(RetentionPolicy.organisation_id == organisation_id)
        .values(signal_days=body.signal_days, verdict_days=body.verdict_days, updated_at=utcnow())
    )
    return policy(session, organisation_id)


def _default_row(organisation_id: int) -> dict[str, object]:
    return {
        "organisation_id": organisation_id,
        "signal_days": DEFAULT_SIGNAL_DAYS,
        "verdict_days": DEFAULT_VERDICT_DAYS,
    }


def prune(
    session: Session,
    organisation_id: int,
    now: dt.datetime | None = None,
    batch: int = BATCH,
    progress: Callable[[Batch], None] | None = None,
) -> Pruned:
    """Prune one organisation under its policy as of ``now``; commits each batch."""
    now = now or utcnow()
    kept = policy(session, organisation_id)
    session.rollback()  # the policy read holds no snapshot through the batches
    pruned = Pruned()

    def run(what: Pass, step: Callable[[Session, int, dt.datetime, int], int], horizon: dt.datetime) -> None:
        while True:
            rows = step(session, organisation_id, horizon, batch)
            session.commit()
            if rows == 0:
                return
            done = Batch(organisation_id, what, rows)
            pruned.add(done)
            if progress is not None:
                progress(done)
            if rows < batch:
                return

    if kept.signal_days is not None:
        run("signals", _drop_signals, now - dt.timedelta(days=kept.signal_days))
    if kept.verdict_days is not None:
        horizon = now - dt.timedelta(days=kept.verdict_days)
        run("verdicts", _delete_verdicts, horizon)
        run("records", _delete_records, horizon)
        run("deliveries", _delete_deliveries, horizon)
    return pruned


def _structures(organisation_id: int) -> Select:
    return select(Structure.id).where(Structure.organisation_id == organisation_id)


def _drop_signals(session: Session, organisation_id: int, horizon: dt.datetime, batch: int) -> int:
    chosen = session.scalars(
        select(Record.id)
        .where(
            Record.structure_id.in_(_structures(organisation_id)),
            Record.acquired_at < horizon,
            Record.signals_pruned_at.is_(None),
        )
        .limit(batch)
    ).all()
    if not chosen:
        return 0
    dropped = session.execute(
        update(Record)
        .where(Record.id.in_(chosen), Record.signals_pruned_at.is_(None))  # not by a concurrent pruning
        .values(x=b"", y=b"", signals_pruned_at=utcnow())
        .execution_options(synchronize_session=False)
    )
    return dropped.rowcount


def _delete_verdicts(session: Session, organisation_id: int, horizon: dt.datetime, batch: int) -> int:
    chosen = session.execute(
        select(Verdict.id, Verdict.structure_id)
        .where(Verdict.structure_id.in_(_structures(organisation_id)), Verdict.acquired_at < horizon)
        .limit(batch)
    ).all()
    if not chosen:
        return 0
    alarms.forget_states(session, {row.structure_id for row in chosen})
    locked = fleet.lock_states(session, (row.structure_id for row in chosen))
    # What was deleted, as returned: a concurrent pruning may have taken some of these already.
    removed = [
        fleet.Removed(*row)
        for row in session.execute(
            delete(Verdict)
            .where(Verdict.id.in_([row.id for row in chosen]))
            .returning(Verdict.id, Verdict.structure_id, Verdict.status, Verdict.acquired_at)
            .execution_options(synchronize_session=False)
        )
    ]
    fleet.uncount_verdicts(session, locked, removed)
    return len(removed)


def _delete_records(session: Session, organisation_id: int, horizon: dt.datetime, batch: int) -> int:
    unreferenced = (
        Record.signals_pruned_at.is_not(None),
        ~exists().where(Verdict.record_id == Record.id),
        ~exists().where(Refinement.record_id == Record.id),
        ~exists().where(RefinementRecord.record_id == Record.id),
    )
    chosen = session.execute(
        select(Record.id, Record.structure_id)
        .where(
            Record.structure_id.in_(_structures(organisation_id)), Record.acquired_at < horizon, *unreferenced
        )
        .limit(batch)
    ).all()
    if not chosen:
        return 0
    # The records are locked before their states, in the order an upload that stores a verdict
    # for one takes them (the verdict's foreign key, then the state row): such an upload finishes
    # first, and the deletion, a statement of its own, then sees its verdict and keeps the record.
    ids = session.scalars(
        select(Record.id)
        .where(Record.id.in_([row.id for row in chosen]))
        .order_by(Record.id)
        .with_for_update()
    ).all()
    fleet.lock_states(session, (row.structure_id for row in chosen))
    deleted = session.scalars(
        delete(Record)
        .where(Record.id.in_(ids), *unreferenced)  # checked again under the locks
        .returning(Record.structure_id)
        .execution_options(synchronize_session=False)
    ).all()
    fleet.uncount_records(session, deleted)
    return len(deleted)


def _delete_deliveries(session: Session, organisation_id: int, horizon: dt.datetime, batch: int) -> int:
    # SETTLED itself, the partial index's own predicate, which a planner can match to the index
    # whatever the statement's parameters (PostgreSQL's generic plans of prepared statements too).
    settled = (Delivery.organisation_id == organisation_id, SETTLED)
    chosen = session.scalars(
        select(Delivery.id).where(*settled, Delivery.created_at < horizon).limit(batch)
    ).all()
    if not chosen:
        return 0
    deleted = session.execute(
        delete(Delivery).where(Delivery.id.in_(chosen), *settled).execution_options(synchronize_session=False)
    )
    return deleted.rowcount


def sweep(session: Session, defer: Defer, every: dt.timedelta, now: dt.datetime | None = None) -> int:
    """Queue a pruning for each organisation not pruned for ``every`` (an organisation is first
    pruned ``every`` after it was created); the number queued. Each claim (a compare-and-set on
    ``last_pruned_at``) is committed with its job, one organisation at a time."""
    if every <= dt.timedelta(0):
        return 0
    now = now or utcnow()
    last = func.coalesce(RetentionPolicy.last_pruned_at, Organisation.created_at)
    due = session.execute(
        select(Organisation.id, RetentionPolicy.organisation_id, RetentionPolicy.last_pruned_at)
        .outerjoin(RetentionPolicy, RetentionPolicy.organisation_id == Organisation.id)
        .where(last <= now - every)
        .order_by(Organisation.id)
        .limit(SWEPT)
    ).all()
    session.rollback()
    queued = 0
    for organisation_id, has_policy, previous in due:
        if has_policy is None:
            claimed = (
                insert_unless_exists(
                    session,
                    RetentionPolicy,
                    {
                        "organisation_id": organisation_id,
                        "signal_days": DEFAULT_SIGNAL_DAYS,
                        "verdict_days": DEFAULT_VERDICT_DAYS,
                        "last_pruned_at": now,
                    },
                    ["organisation_id"],
                    returning=("organisation_id",),
                )
                is not None
            )
        else:
            unchanged = (
                RetentionPolicy.last_pruned_at.is_(None)
                if previous is None
                else RetentionPolicy.last_pruned_at == previous
            )
            claim = (
                update(RetentionPolicy)
                .where(RetentionPolicy.organisation_id == organisation_id, unchanged)
                .values(last_pruned_at=now)
            )
            claimed = session.execute(claim).rowcount == 1
        if claimed:
            defer(session, PRUNE, organisation_id, organisation=organisation_id)
            queued += 1
        session.commit()
    return queued


def organisations(session: Session, name: str | None) -> list[tuple[int, str]]:
    """The organisations a ``narxwatch db prune`` covers: the one named, or all."""
    query = select(Organisation.id, Organisation.name).order_by(Organisation.id)
    if name is not None:
        query = query.where(Organisation.name == name)
    return [(row.id, row.name) for row in session.execute(query)]
