"""Alarms: a structure's rules run over its verdicts after every stored verdict, and the lifecycle
open → acknowledged → resolved, each transition stored and announced.

One verdict is a test at level α, so one record deciding calls a fault about once in twenty
healthy records. The rules (``models.alarms``) look across records instead: *persistence* (k of
the last m verdicts faulty or unknown), a *CUSUM* per fault mode on z = k̂/σ̂k with each
verdict's own σ̂k, designed for a stated number of false alarms a year, and *severity* (an
interval wholly beyond a magnitude). A structure without rules of its own is watched by the
defaults.

Each rule fires or not at each record of the structure's recent history (the newest verdict of
each record, so a re-inspection with new models re-judges it). An alarm opens when a rule fires
on a record among the newest ``clear_after`` and none of its (structure, rule, fault mode) is
unresolved; it resolves by itself once ``clear_after`` records in a row have not fired; after a
resolution the rule looks only at records acquired later, so that the evidence an alarm was
resolved on does not open it again. The CUSUM restarts from zero after each signal, as its design
assumes (``models.alarms``); it starts from zero at the oldest record evaluated.

The records the rules look at, the newest verdict of each of the structure's newest ``WINDOW``
records, are kept in its ``AlarmWindow`` row, updated in the transaction of each verdict: the
rules run over that row, not over the history read again. A verdict is put in its place by
acquisition time, then id (a record uploaded late, or a re-inspection, changes the window as it
changes the history); a structure without a row (before its first verdict after the migration, or
after the retention deleted verdicts it held) has it built from its history.

Evaluations of one structure run one after another (its row lock on PostgreSQL, the single
writer on SQLite), so each reads the window the previous one committed; the database refuses a
second unresolved alarm of the same key anyway.
"""

from __future__ import annotations

import bisect
import datetime as dt
import json
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cache
from typing import Any

import numpy as np
from sqlalchemy import Select, bindparam, delete, exists, func, insert, select, update
from sqlalchemy.orm import Session, aliased, selectinload

from models import alarms as rules_math
from models.errors import InputError
from service.domain import notifications
from service.domain.errors import ConflictError
from service.domain.structures import get_owned, get_structure
from service.schemas import (
    AlarmDetail,
    AlarmOut,
    AlarmPage,
    AlarmRule,
    AlarmRules,
    AlarmRulesOut,
    AlarmTransitionOut,
    CusumDesignOut,
    CusumRule,
    PersistenceRule,
    SeverityRule,
)
from service.security import Principal
from service.tables import (
    UNRESOLVED,
    Alarm,
    AlarmTransition,
    AlarmWindow,
    ApiKey,
    Structure,
    Verdict,
    utcnow,
)
from service.tables import AlarmRule as StoredRule

# Records a rule is evaluated over: the persistence and severity rules need a few, the CUSUM's
# in-control statistic returns to zero every few records, so its start this far back matters
# little; and the evaluation after each verdict stays a few milliseconds.
WINDOW = 200
FLAGGED = ("faulty", "unknown_fault")
DEFAULT_RULES: tuple[AlarmRule, ...] = (
    PersistenceRule(kind="persistence", k=rules_math.PERSISTENCE_K, m=rules_math.PERSISTENCE_M),
    CusumRule(kind="cusum", records_per_day=rules_math.RECORDS_PER_DAY, shift=rules_math.DESIGN_SHIFT),
    SeverityRule(kind="severity"),
)
# The largest CUSUM threshold (σ units) the service designs for: beyond it a chart is slow to detect
# anything, and the design's search takes seconds.
MAX_THRESHOLD = 16.0
MAX_PAGE = 1000


@dataclass(frozen=True)
class Point:
    """A record's newest verdict, as the rules read it."""

    record_id: int
    verdict_id: int
    acquired_at: dt.datetime
    status: str
    reference_mode: str | None
    interval: tuple[float, float] | None
    modes: dict[str, tuple[float, float, float]]  # name → (k̂, σ̂k, σ̂k of the record alone)

    @property
    def order(self) -> tuple[dt.datetime, int]:
        """Where the point stands in its structure's history: by acquisition, then verdict id."""
        return self.acquired_at, self.verdict_id


def point(
    verdict_id: int,
    record_id: int,
    acquired_at: dt.datetime,
    status: str,
    reference_mode: str | None,
    interval_low: float | None,
    interval_high: float | None,
    modes: list[dict[str, Any]],
) -> Point:
    """A verdict's point, from its columns: the fault modes whose z = k̂/σ̂k is a number."""
    return Point(
        record_id=record_id,
        verdict_id=verdict_id,
        acquired_at=acquired_at.astimezone(dt.UTC),
        status=status,
        reference_mode=reference_mode,
        interval=(interval_low, interval_high) if interval_low is not None else None,  # type: ignore[arg-type]
        modes={
            m["name"]: (m["k_hat"], m["sigma_k"], m["sigma_k_record"])
            for m in modes
            if m["sigma_k"] > 0 and math.isfinite(m["k_hat"] / m["sigma_k"])
        },
    )


@dataclass(frozen=True)
class Firing:
    """Where a rule fired: ``fired`` per record of ``points``; for the CUSUM, the index of the
    first record of each signal's drift, and its statistic (the larger side) after each record."""

    fault_mode: str | None
    points: list[Point]
    fired: list[bool]
    drift_starts: dict[int, int]
    statistic: list[float] = field(default_factory=list)


@dataclass(frozen=True)
class CusumSeries:
    """A fault mode's CUSUM as the rules ran it, for the structure's k̂ chart."""

    fault_mode: str
    acquired_at: list[dt.datetime]
    statistic: list[float]
    threshold: float


# --- rules ------------------------------------------------------------------------------------


# The statements run after every verdict, built once (their compiled forms are cached by
# SQLAlchemy; building the expressions anew cost more than running them).
RULES_OF = select(StoredRule.parameters).where(StoredRule.structure_id == bindparam("structure_id"))
WINDOW_OF = select(AlarmWindow.points).where(AlarmWindow.structure_id == bindparam("structure_id"))
NEW_WINDOW = insert(AlarmWindow)
KEEP_WINDOW = (
    update(AlarmWindow.__table__)
    .where(AlarmWindow.__table__.c.structure_id == bindparam("structure"))
    .values(points=bindparam("window"))
)
UNRESOLVED_OF = select(Alarm).where(Alarm.structure_id == bindparam("structure_id"), UNRESOLVED)
RESOLVED_THROUGH = (
    select(Alarm.rule_kind, Alarm.fault_mode, func.max(Alarm.evaluated_through))
    .where(Alarm.structure_id == bindparam("structure_id"), Alarm.state == "resolved")
    .group_by(Alarm.rule_kind, Alarm.fault_mode)
)
LOCK = select(Structure.id).where(Structure.id == bindparam("structure_id")).with_for_update(key_share=True)


def rules_of(session: Session, structure_id: int) -> tuple[list[AlarmRule], bool]:
    """The structure's rules and whether they are the defaults (it has none of its own)."""
    stored = session.scalars(RULES_OF, {"structure_id": structure_id})
    rules = [AlarmRules.model_validate({"rules": [parameters]}).rules[0] for parameters in stored]
    if not rules:
        return list(DEFAULT_RULES), True
    return sorted(rules, key=lambda rule: [r.kind for r in DEFAULT_RULES].index(rule.kind)), False


def get_rules(session: Session, principal: Principal, structure_id: int) -> AlarmRulesOut:
    get_structure(session, principal, structure_id)
    rules, defaults = rules_of(session, structure_id)
    return _rules_out(session, structure_id, rules, defaults)


def set_rules(session: Session, principal: Principal, structure_id: int, body: AlarmRules) -> AlarmRulesOut:
    """Replace the structure's rules and judge its history by them at once; unresolved alarms of
    a kind no longer watched are resolved as ``rule_removed``."""
    structure = get_structure(session, principal, structure_id)
    for rule in body.rules:
        if isinstance(rule, CusumRule):  # a design that exists without the models' error, or a 422
            cusum_design(rule, [])
    lock(session, structure_id)
    session.execute(delete(StoredRule).where(StoredRule.structure_id == structure_id))
    session.add_all(
        StoredRule(structure_id=structure_id, kind=rule.kind, parameters=rule.model_dump(mode="json"))
        for rule in body.rules
    )
    session.flush()
    kinds = {rule.kind for rule in body.rules}
    for alarm in _unresolved(session, structure_id).values():
        if alarm.rule_kind not in kinds:
            _resolve(session, structure, alarm, "rule_removed", None, None)
    evaluate(session, structure)
    return _rules_out(session, structure_id, body.rules, False)


def _rules_out(session: Session, structure_id: int, rules: list[AlarmRule], defaults: bool) -> AlarmRulesOut:
    cusum = next((rule for rule in rules if isinstance(rule, CusumRule)), None)
    design, problem = None, None
    if cusum is not None:
        points = window(session, structure_id)
        try:
            design = CusumDesignOut(modes=_mode_count(points), **vars(cusum_design(cusum, points)))
        except InputError as refusal:
            problem = str(refusal)
    return AlarmRulesOut(
        structure_id=structure_id, defaults=defaults, rules=rules, cusum_design=design, cusum_problem=problem
    )


def cusum_design(rule: CusumRule, points: list[Point]) -> rules_math.CusumDesign:
    """The CUSUM each fault mode is watched with, for the models of the verdicts ``points``.

    The structure's false alarms a year are shared among its charts (their rates add up at most),
    so each runs as many times longer in control as there are modes; and the share of σ̂k² that
    the models' own error makes common to all records (``_common_share``, to two decimals as
    ``models.alarms.default_rules`` takes it) raises the threshold
    that keeps that rate. ``InputError`` says why when no CUSUM within ``MAX_THRESHOLD`` can be
    designed: then the CUSUM does not run (the rules' API says why), and the other rules still do.
    """
    records_per_year = 365.0 * rule.records_per_day
    arl = _mode_count(points) * records_per_year / rule.false_alarms_per_year
    design = _design(arl, rule.shift, round(_common_share(points), 2))
    if isinstance(design, str):
        raise InputError(design)
    return design


@cache
def _design(arl: float, shift: float, share: float) -> rules_math.CusumDesign | str:
    """A design, or why there is none; both kept. A design needing a threshold beyond
    ``MAX_THRESHOLD`` is refused after one run-length evaluation, before any search: the search's
    cost grows with the threshold, to seconds beyond it."""
    if rules_math.in_control_arl(MAX_THRESHOLD, shift / 2.0, share) < arl:
        common = (
            f": the fault-mode models' own error is {share:.0%} of σ̂k², the same in every record"
            if share > 0
            else ""
        )
        return (
            f"a CUSUM keeping {arl:.0f} records between false alarms would need a threshold beyond "
            f"{MAX_THRESHOLD:g} σ{common}. Raise the shift, allow more false alarms a year, or train "
            "the fault-mode models on more experiments"
        )
    try:
        return rules_math.design_cusum(arl, shift, share)
    except InputError as refusal:
        return str(refusal)


def _common_share(points: list[Point]) -> float:
    """The median over the healthy records (all, if none is) of the largest mode's common share:
    the models' error grows away from the healthy state, and a design for the healthy structure
    must not move because a fault is under way."""
    healthy = [p for p in points if p.status == "healthy" and p.modes]
    shares = [
        max(rules_math.common_share(sigma, alone) for _, sigma, alone in point.modes.values())
        for point in healthy or [p for p in points if p.modes]
    ]
    return float(np.median(shares)) if shares else 0.0


# --- evaluation -------------------------------------------------------------------------------


def evaluate(session: Session, structure: Structure, verdict: Point | None = None) -> None:
    """Run the structure's rules over its recent verdicts; open, keep or resolve its alarms.

    Called in the transaction that stored a verdict, ``verdict`` (and when the rules change,
    with none), after the verdict's insert: only flushes. Every transition is announced through
    :func:`service.domain.notifications.notify`, delivered after the commit.
    """
    lock(session, structure.id)
    points = window(session, structure.id, verdict)
    if not points:
        return
    rules, _ = rules_of(session, structure.id)
    unresolved = _unresolved(session, structure.id)
    since = _resolved_through(session, structure.id)
    for rule in rules:
        for firing in _firings(rule, points, since):
            key = (rule.kind, firing.fault_mode)
            _apply(session, structure, rule, firing, points, unresolved.get(key))


def _apply(
    session: Session,
    structure: Structure,
    rule: AlarmRule,
    firing: Firing,
    points: list[Point],
    alarm: Alarm | None,
) -> None:
    fired = [i for i, f in enumerate(firing.fired) if f]
    newest = firing.points[-1]
    quiet = len(firing.points) - 1 - fired[-1] if fired else len(firing.points)
    if alarm is not None:
        alarm.evaluated_through = max(alarm.evaluated_through, newest.acquired_at)
        if quiet >= rule.clear_after:
            _resolve(session, structure, alarm, "cleared", None, None)
        return
    if not fired or quiet >= rule.clear_after:
        return
    first = fired[-1]  # the first firing of the current run: no quiet stretch of clear_after since
    for earlier in reversed(fired[:-1]):
        if first - earlier > rule.clear_after:
            break
        first = earlier
    trigger = firing.points[first]
    drift = firing.drift_starts.get(first)
    alarm = Alarm(
        structure_id=structure.id,
        organisation_id=structure.organisation_id,
        rule_kind=rule.kind,
        rule=_rule_document(rule, points),
        fault_mode=firing.fault_mode,
        state="open",
        opened_at=utcnow(),
        record_id=trigger.record_id,
        triggered_at=trigger.acquired_at,
        drift_started_at=firing.points[drift].acquired_at if drift is not None else None,
        evaluated_through=newest.acquired_at,
    )
    alarm.transitions.append(AlarmTransition(from_state=None, to_state="open", at=alarm.opened_at))
    session.add(alarm)
    session.flush()
    _announce(session, structure, alarm, "alarm.opened")


def _rule_document(rule: AlarmRule, points: list[Point]) -> dict[str, Any]:
    """The rule as it fired; a CUSUM's with the design it ran with."""
    document = rule.model_dump(mode="json")
    if isinstance(rule, CusumRule):
        document["design"] = vars(cusum_design(rule, points)) | {"modes": _mode_count(points)}
    return document


def _firings(
    rule: AlarmRule, points: list[Point], since: dict[tuple[str, str | None], dt.datetime]
) -> Iterator[Firing]:
    """For each fault mode the rule watches, whether it fired at each record acquired after the
    last resolution of its alarm."""

    def after(mode: str | None) -> list[Point]:
        start = since.get((rule.kind, mode))
        return [p for p in points if start is None or p.acquired_at > start]

    if isinstance(rule, PersistenceRule):
        chosen = after(None)
        fired = rules_math.persistence_path([p.status in FLAGGED for p in chosen], rule.k, rule.m)
        if chosen:
            yield Firing(None, chosen, fired, {})
        return
    if isinstance(rule, CusumRule):
        try:
            design = cusum_design(rule, points)
        except InputError:  # GET …/alarm-rules and the structure's page say why
            return
    for mode in sorted({name for p in points for name in p.modes}):
        chosen = after(mode)
        if isinstance(rule, SeverityRule):
            chosen_fired = [_severe(p, mode, rule.threshold) for p in chosen]
            if chosen:
                yield Firing(mode, chosen, chosen_fired, {})
        else:
            with_mode = [p for p in chosen if mode in p.modes]
            if with_mode:
                yield _cusum_firing(mode, with_mode, design)


def _severe(point: Point, mode: str, threshold: float) -> bool:
    if point.reference_mode != mode or point.interval is None:
        return False
    low, high = point.interval
    return rules_math.severity(low, high, threshold) or rules_math.severity(low, high, -threshold)


def _cusum_firing(mode: str, points: list[Point], design: rules_math.CusumDesign) -> Firing:
    """The chart's signals, restarting from zero after each one (as its design assumes)."""
    z = np.array([k_hat / sigma for k_hat, sigma, _ in (p.modes[mode] for p in points)])
    chart = rules_math.cusum_chart(z, design)
    fired = [False] * len(points)
    for at in chart.alarms:
        fired[at] = True
    drift_starts = dict(zip(chart.alarms, chart.drift_starts, strict=True))
    return Firing(mode, points, fired, drift_starts, chart.statistic.tolist())


def cusum_series(session: Session, structure_id: int) -> list[CusumSeries]:
    """Each fault mode's CUSUM statistic over the records the rules look at, with its threshold;
    none when the structure has no CUSUM rule."""
    rules, _ = rules_of(session, structure_id)
    rule = next((r for r in rules if isinstance(r, CusumRule)), None)
    points = window(session, structure_id)
    if rule is None or not points:
        return []
    try:
        threshold = cusum_design(rule, points).threshold
    except InputError:
        return []
    return [
        CusumSeries(
            firing.fault_mode or "", [p.acquired_at for p in firing.points], firing.statistic, threshold
        )
        for firing in _firings(rule, points, _resolved_through(session, structure_id))
    ]


def window(session: Session, structure_id: int, verdict: Point | None = None) -> list[Point]:
    """The points the structure's rules run over (:func:`newest_points`), from its kept window
    with ``verdict``, just stored, put in its place; the window is kept so. Built from the
    history when the structure has none kept: the history holds ``verdict`` already. Read-only
    without ``verdict``: a structure without a kept window is read from its history then."""
    kept = session.execute(WINDOW_OF, {"structure_id": structure_id}).scalar_one_or_none()
    if kept is None:
        points = newest_points(session, structure_id, WINDOW)
        if verdict is not None:
            rows = [_row(p) for p in points]
            session.execute(NEW_WINDOW, {"structure_id": structure_id, "points": _dumps(rows)})
        return points
    rows = json.loads(kept)
    if verdict is not None and _merge(rows, _row(verdict)):
        session.execute(KEEP_WINDOW, {"structure": structure_id, "window": _dumps(rows)})
    return [_point_of(row) for row in rows]


# A kept point: [record id, verdict id, acquired_at in µs since the epoch, status, reference mode,
# interval or None, [[mode, k̂, σ̂k, σ̂k of the record alone], …]]. Microseconds, the resolution
# of the databases' timestamps, keep acquired_at exact and cheap to read.
_RECORD, _VERDICT, _AT = 0, 1, 2
EPOCH = dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
MICROSECOND = dt.timedelta(microseconds=1)


def _merge(rows: list[list[Any]], new: list[Any]) -> bool:
    """Put the kept point ``new`` of a verdict just stored in its place among ``rows`` (a
    structure's newest records' newest verdicts, oldest first), keeping the newest ``WINDOW``;
    False when that leaves them as they are: a later verdict of its record is there already
    (stored concurrently, committed first), or the window is full of newer ones. Its record's
    earlier verdict, if there, gives way to it."""
    order = (new[_AT], new[_VERDICT])
    earlier = next((i for i, row in enumerate(rows) if row[_RECORD] == new[_RECORD]), None)
    if earlier is not None:
        if rows[earlier][_VERDICT] > new[_VERDICT]:
            return False
        del rows[earlier]
    elif len(rows) >= WINDOW and order < (rows[0][_AT], rows[0][_VERDICT]):
        return False
    rows.insert(bisect.bisect([(row[_AT], row[_VERDICT]) for row in rows], order), new)
    del rows[:-WINDOW]
    return True


def _row(p: Point) -> list[Any]:
    modes = [[name, *figures] for name, figures in p.modes.items()]
    at = (p.acquired_at - EPOCH) // MICROSECOND
    return [p.record_id, p.verdict_id, at, p.status, p.reference_mode, p.interval, modes]


def _point_of(row: list[Any]) -> Point:
    record_id, verdict_id, at, status, reference_mode, interval, modes = row
    return Point(
        record_id=record_id,
        verdict_id=verdict_id,
        acquired_at=EPOCH + dt.timedelta(microseconds=at),
        status=status,
        reference_mode=reference_mode,
        interval=(interval[0], interval[1]) if interval is not None else None,
        modes={name: (k_hat, sigma, alone) for name, k_hat, sigma, alone in modes},
    )


def _dumps(rows: list[list[Any]]) -> str:
    return json.dumps(rows, separators=(",", ":"))


def newest_points(session: Session, structure_id: int, count: int) -> list[Point]:
    """The newest verdict of each of the structure's newest ``count`` inspected records, oldest
    first (a re-inspection with new models re-judges a record: its earlier verdicts are passed
    over, each through the index on the record), read from its history."""
    later = aliased(Verdict)
    rows = session.execute(
        select(
            Verdict.id,
            Verdict.record_id,
            Verdict.acquired_at,
            Verdict.status,
            Verdict.reference_mode,
            Verdict.interval_low,
            Verdict.interval_high,
            Verdict.modes,
        )
        .where(
            Verdict.structure_id == structure_id,
            ~exists().where(later.record_id == Verdict.record_id, later.id > Verdict.id),
        )
        .order_by(Verdict.acquired_at.desc(), Verdict.id.desc())
        .limit(count)
    ).all()
    return [point(*row) for row in reversed(rows)]


def _mode_count(points: list[Point]) -> int:
    """The fault modes the newest verdict was judged against (one before any verdict): the
    number of CUSUM charts that share the structure's false alarms."""
    return max(1, len(points[-1].modes)) if points else 1


def _unresolved(session: Session, structure_id: int) -> dict[tuple[str, str | None], Alarm]:
    alarms = session.scalars(UNRESOLVED_OF, {"structure_id": structure_id})
    return {(alarm.rule_kind, alarm.fault_mode): alarm for alarm in alarms}


def _resolved_through(session: Session, structure_id: int) -> dict[tuple[str, str | None], dt.datetime]:
    rows = session.execute(RESOLVED_THROUGH, {"structure_id": structure_id})
    return {(kind, mode): through for kind, mode, through in rows}


def forget_windows(session: Session, structure_ids: set[int]) -> None:
    """Drop the kept windows of structures whose verdicts are about to be deleted (by the
    retention), each rebuilt from what is left of its history the next time its rules run. The
    structures are locked first, in order of id, as :func:`lock` locks one: no evaluation reads
    a window, or builds one from a history, that the deletion is changing."""
    ordered = sorted(structure_ids)
    session.execute(
        select(Structure.id)
        .where(Structure.id.in_(ordered))
        .order_by(Structure.id)
        .with_for_update(key_share=True)
    )
    session.execute(delete(AlarmWindow).where(AlarmWindow.structure_id.in_(ordered)))


def lock(session: Session, structure_id: int) -> None:
    """The structure's row lock (``FOR NO KEY UPDATE``, as trainings take it): evaluations of one
    structure run one after another, each seeing the alarms the previous one committed; uploads,
    whose foreign keys take ``KEY SHARE`` locks, are not held up. SQLite has one writer.

    Taken before the structure's state row (``service.domain.fleet``) by every transaction that
    takes both, so that none waits for the other in a cycle: a stored verdict's alarms, then its
    counts (``inspections.store_verdict``); an upload inspected at once locks it before storing
    its record (``ingest``)."""
    session.execute(LOCK, {"structure_id": structure_id})


# --- lifecycle --------------------------------------------------------------------------------


def acknowledge(session: Session, principal: Principal, alarm_id: int, note: str) -> Alarm:
    alarm = _get(session, principal, alarm_id)
    if alarm.state != "open":
        raise ConflictError(f"alarm {alarm_id} is {alarm.state}; only an open alarm can be acknowledged")
    structure = get_structure(session, principal, alarm.structure_id)
    key = session.get(ApiKey, principal.key_id)
    alarm.state, alarm.acknowledged_at = "acknowledged", utcnow()
    alarm.acknowledged_key, alarm.acknowledgement_note = key, note or None
    alarm.transitions.append(
        AlarmTransition(
            from_state="open", to_state="acknowledged", at=alarm.acknowledged_at, key=key, note=note or None
        )
    )
    session.flush()
    _announce(session, structure, alarm, "alarm.acknowledged")
    return alarm


def resolve(session: Session, principal: Principal, alarm_id: int, note: str) -> Alarm:
    alarm = _get(session, principal, alarm_id)
    if alarm.state == "resolved":
        raise ConflictError(f"alarm {alarm_id} is resolved already ({alarm.resolution})")
    structure = get_structure(session, principal, alarm.structure_id)
    _resolve(session, structure, alarm, "by_hand", session.get(ApiKey, principal.key_id), note or None)
    return alarm


def _resolve(
    session: Session, structure: Structure, alarm: Alarm, how: str, key: ApiKey | None, note: str | None
) -> None:
    """``key`` None: the service resolved it (the rule cleared, or was removed)."""
    now = utcnow()
    alarm.transitions.append(
        AlarmTransition(from_state=alarm.state, to_state="resolved", at=now, key=key, note=note)
    )
    alarm.state, alarm.resolved_at, alarm.resolved_key = "resolved", now, key
    alarm.resolution, alarm.resolution_note = how, note
    session.flush()
    _announce(session, structure, alarm, "alarm.resolved")


def _announce(session: Session, structure: Structure, alarm: Alarm, event: str) -> None:
    notifications.notify(session, structure.organisation_id, event, alarm_out(alarm).model_dump(mode="json"))


# --- reading ----------------------------------------------------------------------------------

LOADED = (
    selectinload(Alarm.acknowledged_key),
    selectinload(Alarm.resolved_key),
)


def _get(session: Session, principal: Principal, alarm_id: int) -> Alarm:
    return get_owned(session, principal, Alarm, alarm_id, "alarm", options=list(LOADED))


def get_alarm(session: Session, principal: Principal, alarm_id: int) -> AlarmDetail:
    alarm = get_owned(
        session,
        principal,
        Alarm,
        alarm_id,
        "alarm",
        options=[*LOADED, selectinload(Alarm.transitions).selectinload(AlarmTransition.key)],
    )
    transitions = [
        AlarmTransitionOut(
            from_state=t.from_state,  # type: ignore[arg-type]
            to_state=t.to_state,  # type: ignore[arg-type]
            at=t.at,
            by=t.key.prefix if t.key is not None else None,
            note=t.note,
        )
        for t in alarm.transitions
    ]
    return AlarmDetail(**alarm_out(alarm).model_dump(), transitions=transitions)


def list_alarms(
    session: Session,
    principal: Principal,
    *,
    structure_id: int | None = None,
    state: str | None = None,
    rule_kind: str | None = None,
    fault_mode: str | None = None,
    start: dt.datetime | None = None,
    end: dt.datetime | None = None,
    cursor: int | None = None,
    limit: int = 100,
) -> AlarmPage:
    """The organisation's alarms opened in [start, end), newest first, ``limit`` at a time."""
    if structure_id is not None:
        get_structure(session, principal, structure_id)
        query = select(Alarm).where(Alarm.structure_id == structure_id)
    else:
        query = select(Alarm).where(Alarm.organisation_id == principal.organisation_id)
    if state is not None:
        query = query.where(Alarm.state == state)
    if rule_kind is not None:
        query = query.where(Alarm.rule_kind == rule_kind)
    if fault_mode is not None:
        query = query.where(Alarm.fault_mode == fault_mode)
    if start is not None:
        query = query.where(Alarm.opened_at >= start)
    if end is not None:
        query = query.where(Alarm.opened_at < end)
    if cursor is not None:
        query = query.where(Alarm.id < cursor)
    rows = list(session.scalars(query.order_by(Alarm.id.desc()).limit(limit + 1).options(*LOADED)))
    page = rows[:limit]
    return AlarmPage(
        items=[alarm_out(a) for a in page], next_cursor=page[-1].id if len(rows) > limit else None
    )


def unresolved_alarms(
    session: Session, principal: Principal, structure_id: int | None = None, limit: int | None = None
) -> list[Alarm]:
    """The caller's open and acknowledged alarms (of one structure), oldest first, at most ``limit``
    (None: all): the dashboard's."""
    query = _unresolved_of(select(Alarm), principal, structure_id).order_by(Alarm.id).limit(limit)
    return list(session.scalars(query.options(*LOADED)))


def count_unresolved(session: Session, principal: Principal) -> int:
    """How many open and acknowledged alarms the caller's organisation has."""
    return session.scalar(_unresolved_of(select(func.count(Alarm.id)), principal, None)) or 0


def _unresolved_of(query: Select[Any], principal: Principal, structure_id: int | None) -> Select[Any]:
    # UNRESOLVED itself, the partial indexes' predicate: as a bound parameter, a generic plan
    # (a statement prepared after several runs) could not use them.
    query = query.where(UNRESOLVED)
    if structure_id is None:
        # Through the structures, each probing the index of its unresolved alarms: by the
        # organisation's index, every alarm it ever had would be read and its state filtered.
        return query.join(Structure, Structure.id == Alarm.structure_id).where(
            Structure.organisation_id == principal.organisation_id
        )
    return query.where(Alarm.structure_id == structure_id)


def alarm_out(alarm: Alarm) -> AlarmOut:
    return AlarmOut(
        id=alarm.id,
        structure_id=alarm.structure_id,
        rule_kind=alarm.rule_kind,  # type: ignore[arg-type]
        rule=alarm.rule,
        fault_mode=alarm.fault_mode,
        state=alarm.state,  # type: ignore[arg-type]
        opened_at=alarm.opened_at,
        record_id=alarm.record_id,
        triggered_at=alarm.triggered_at,
        drift_started_at=alarm.drift_started_at,
        acknowledged_at=alarm.acknowledged_at,
        acknowledged_by=alarm.acknowledged_key.prefix if alarm.acknowledged_key is not None else None,
        acknowledgement_note=alarm.acknowledgement_note,
        resolved_at=alarm.resolved_at,
        resolved_by=alarm.resolved_key.prefix if alarm.resolved_key is not None else None,
        resolution=alarm.resolution,  # type: ignore[arg-type]
        resolution_note=alarm.resolution_note,
    )
