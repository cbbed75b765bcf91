"""Alarms: a structure's rules run over its verdicts after every stored verdict, and the lifecycle
open → acknowledged → resolved, each transition stored and announced.

One verdict is a test at level α, so one record deciding calls a fault about once in twenty
healthy records. The rules (``models.alarms``) look across records instead: *persistence* (k of
the last m verdicts faulty, unknown or an anomaly), a *CUSUM* per fault mode on z = k̂/σ̂k with each
verdict's own σ̂k, designed for a stated number of false alarms a year, and *severity* (an
interval wholly beyond a magnitude). A structure without rules of its own is watched by the
defaults.

Each rule fires or not at each record of the structure, in order of acquisition (the newest
verdict of each record, so a re-inspection with new models re-judges it). An alarm opens when a
rule fires on a record among the newest ``clear_after`` and none of its (structure, rule, fault
mode) is unresolved; it resolves by itself once ``clear_after`` records in a row have not fired;
after a resolution the rule counts only records acquired later, so that the evidence an alarm
was resolved on does not open it again. The CUSUM is a running one over the records, restarting
from zero only at its signals, as its design assumes (``models.alarms``), and where its alarm
resolved. Its design takes the fault modes of the newest verdict (the charts sharing the
structure's false alarms) and the median common share of σ̂k² of the newest ``WINDOW`` healthy
verdicts (of all verdicts until one is healthy), both as they stood at each record.

A fault mode whose k̂ sits at the limit of the range its model searches (the verdict's
``at_range_limit``) was not measured: the search stopped at the edge, and z = k̂/σ̂k there says how
far the edge is, not the fault. Such a record does not step that mode's CUSUM (its sums and the
records it counted stay as they were; a fault that large is for the persistence and severity rules,
or for a model trained over a wider range), and the rules' API names the mode and says why while
the newest record is one. When no CUSUM can be designed for the structure as it stands (the rules
changed, or the models' common error grew), the CUSUM does not run, the rules' API says why, and
its unresolved alarms are resolved as ``rule_not_running`` with that reason: no alarm stays open
on a chart that stopped.

What each rule needs to go on is kept in the structure's ``AlarmState`` row (:class:`Kept`),
updated in the transaction of each verdict: per rule and fault mode a :class:`Track` (a CUSUM's
two sums and where its drift began, persistence's last m outcomes, the current run of firings,
the unresolved alarm), the design's inputs, and the newest verdict counted. A verdict newer than
that one, of a record with no other verdict (an upload, the common case), moves each track one
record on, whatever the length of the history. Any other verdict — a record uploaded late, a
re-inspection, a verdict whose later sibling was committed first — and a structure without a
kept state (after the migration, after the retention deleted verdicts, after an alarm was
resolved by hand) or whose rules changed, has the state rebuilt from the history
(:func:`_replay`): the newest verdict of each of the newest ``WINDOW`` records counted in order,
each track from its rule's last resolution on. That rebuild is also the reference the kept state
is tested against; it differs from the running state only where a CUSUM had not come back to
zero within those ``WINDOW`` records.

Evaluations of one structure run one after another (its row lock on PostgreSQL, the single
writer on SQLite), so each reads the state the previous one committed; the database refuses a
second unresolved alarm of the same key anyway.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import statistics
from dataclasses import dataclass, field
from functools import cache, lru_cache
from typing import Any

from sqlalchemy import Select, bindparam, delete, exists, func, insert, select, update
from sqlalchemy.orm import Session, aliased, selectinload

from models import alarms as rules_math
from models.errors import InputError
from service.db import hold_writer_gate
from service.domain import notifications
from service.domain.errors import ConflictError
from service.domain.paging import Page
from service.domain.structures import get_owned, get_structure
from service.schemas import (
    AlarmOut,
    AlarmRule,
    AlarmRules,
    CusumRule,
    PersistenceRule,
    SeverityRule,
)
from service.security import Principal
from service.tables import (
    UNRESOLVED,
    Alarm,
    AlarmState,
    AlarmTransition,
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
# The statuses that find a fault: an anomaly (a healthy baseline's judgement alone) as much as the
# chain's.
FLAGGED = ("faulty", "unknown_fault", "anomaly")
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
    pinned: frozenset[str] = frozenset()  # the modes whose k̂ sits at its model's range limit

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
        pinned=frozenset(m["name"] for m in modes if m.get("at_range_limit")),
    )


@dataclass(frozen=True)
class CusumSeries:
    """A fault mode's CUSUM as the rules ran it, for the structure's k̂ chart."""

    fault_mode: str
    acquired_at: list[dt.datetime]
    statistic: list[float]
    threshold: float


@dataclass(frozen=True, kw_only=True)
class StructureCusumDesign(rules_math.CusumDesign):
    """The CUSUM each of a structure's ``modes`` fault modes is watched with (:func:`cusum_design`)."""

    modes: int


@dataclass(frozen=True)
class RuleSet:
    """A structure's alarm rules as they run: the rules (the service's defaults when ``defaults``),
    the CUSUM's design or why it does not run (``cusum_problem``), and the fault modes whose CUSUM
    the newest record did not step, each with why."""

    structure_id: int
    defaults: bool
    rules: list[AlarmRule]
    cusum_design: StructureCusumDesign | None
    cusum_problem: str | None
    cusum_skipped: dict[str, str]


# --- rules ------------------------------------------------------------------------------------


# The statements run after every verdict, built once (their compiled forms are cached by
# SQLAlchemy; building the expressions anew cost more than running them), on the tables rather
# than the mapped classes, which would run the session's ORM machinery for a row or two.
RULES, KEPT, ALARMS = StoredRule.__table__, AlarmState.__table__, Alarm.__table__
VERDICTS, STRUCTURES = Verdict.__table__, Structure.__table__
RULES_OF = select(RULES.c.parameters).where(RULES.c.structure_id == bindparam("structure_id"))
STATE_OF = select(KEPT.c.state).where(KEPT.c.structure_id == bindparam("structure_id"))
NEW_STATE = insert(KEPT)
KEEP_STATE = (
    update(KEPT).where(KEPT.c.structure_id == bindparam("structure")).values(state=bindparam("state"))
)
# An unresolved alarm's newest record counted, one row per alarm (executemany).
THROUGH = (
    update(ALARMS).where(ALARMS.c.id == bindparam("alarm")).values(evaluated_through=bindparam("through"))
)
OTHER_VERDICT = select(VERDICTS.c.id).where(
    VERDICTS.c.record_id == bindparam("record_id"), VERDICTS.c.id != bindparam("verdict_id")
)
UNRESOLVED_OF = select(Alarm).where(Alarm.structure_id == bindparam("structure_id"), UNRESOLVED)
RESOLVED_THROUGH = (
    select(Alarm.rule_kind, Alarm.fault_mode, func.max(Alarm.evaluated_through))
    .where(Alarm.structure_id == bindparam("structure_id"), Alarm.state == "resolved")
    .group_by(Alarm.rule_kind, Alarm.fault_mode)
)
LOCK = (
    select(STRUCTURES.c.id)
    .where(STRUCTURES.c.id == bindparam("structure_id"))
    .with_for_update(key_share=True)
)


def rules_of(session: Session, structure_id: int) -> tuple[list[AlarmRule], bool]:
    """The structure's rules and whether they are the defaults (it has none of its own)."""
    rules = [
        _rule(json.dumps(parameters, sort_keys=True))
        for parameters in session.scalars(RULES_OF, {"structure_id": structure_id})
    ]
    if not rules:
        return list(DEFAULT_RULES), True
    return sorted(rules, key=lambda rule: [r.kind for r in DEFAULT_RULES].index(rule.kind)), False


@lru_cache(maxsize=1024)
def _rule(parameters: str) -> AlarmRule:
    """A stored rule's parameters, validated once: every verdict reads its structure's rules.
    Bounded: admins may store any number of distinct rules."""
    return AlarmRules.model_validate({"rules": [json.loads(parameters)]}).rules[0]


def get_rules(session: Session, principal: Principal, structure_id: int, limit: dt.datetime) -> RuleSet:
    get_structure(session, principal, structure_id)
    rules, defaults = rules_of(session, structure_id)
    return _rules_out(session, structure_id, rules, defaults, limit)


def set_rules(
    session: Session, principal: Principal, structure_id: int, body: AlarmRules, limit: dt.datetime
) -> RuleSet:
    """Replace the structure's rules and judge its history by them at once (the verdicts acquired
    up to ``limit``, as :func:`evaluate` reads them); unresolved alarms of a kind no longer
    watched are resolved as ``rule_removed``."""
    structure = get_structure(session, principal, structure_id)
    for rule in body.rules:
        if isinstance(rule, CusumRule):  # a design that exists without the models' error, or a 422
            cusum_design(rule, 1, 0.0)
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
    evaluate(session, structure, limit)
    return _rules_out(session, structure_id, body.rules, False, limit)


def _rules_out(
    session: Session, structure_id: int, rules: list[AlarmRule], defaults: bool, limit: dt.datetime
) -> RuleSet:
    cusum = next((rule for rule in rules if isinstance(rule, CusumRule)), None)
    design, problem, skipped = None, None, {}
    if cusum is not None:
        kept = _standing(session, structure_id, rules, limit)
        try:
            design = StructureCusumDesign(
                modes=kept.modes, **vars(cusum_design(cusum, kept.modes, kept.share()))
            )
        except InputError as refusal:
            problem = str(refusal)
        else:
            skipped = {mode: _misfit_reason(mode, kept.localised) for mode in kept.misfit} | {
                mode: _pinned_reason(mode, k_hat) for mode, k_hat in kept.pinned.items()
            }
    return RuleSet(structure_id, defaults, rules, design, problem, skipped)


def _misfit_reason(mode: str, localised: str | None) -> str:
    return (
        f"the newest record's fault is localised to fault mode {localised!r}: fault mode {mode!r}'s "
        "model does not describe it, and its k̂ moves with any fault. The record does not step this "
        "mode's CUSUM"
    )


def _pinned_reason(mode: str, k_hat: float) -> str:
    return (
        f"the newest record's estimate for fault mode {mode!r}, k̂ = {k_hat:g} %, sits at the limit of "
        "the range its model searches: the search stopped there, it did not measure the magnitude. "
        "The record does not step this mode's CUSUM; a record measured within the range does. A "
        "fault this large is for the other rules, or for a model trained over a wider range"
    )


def cusum_design(rule: CusumRule, modes: int, share: float) -> rules_math.CusumDesign:
    """The CUSUM each fault mode is watched with, for ``modes`` fault modes (those the newest
    verdict was judged against: one before any) and the common share ``share`` (:meth:`Kept.share`).

    The structure's false alarms a year are shared among its charts (their rates add up at most),
    so each runs as many times longer in control as there are modes; and the share of σ̂k² that
    the models' own error makes common to all records (to two decimals as
    ``models.alarms.default_rules`` takes it) raises the threshold that keeps that rate.
    ``InputError`` says why when no CUSUM within ``MAX_THRESHOLD`` can be designed: then the CUSUM
    does not run (the rules' API says why), and the other rules still do.
    """
    records_per_year = 365.0 * rule.records_per_day
    arl = modes * records_per_year / rule.false_alarms_per_year
    design = _design(arl, rule.shift, round(share, 2))
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


# --- kept state -------------------------------------------------------------------------------


@dataclass
class Track:
    """One rule's state for one fault mode (``None``: persistence, which has none) of a structure.

    Times are microseconds since the epoch (the databases' resolution: exact, and cheap to keep).
    ``after``: only records acquired later count (the ``evaluated_through`` of the rule's last
    resolved alarm); ``through``: the newest record counted; ``quiet``: records counted since the
    last firing (all of them, if none fired); ``first``: the current run of firings' first one,
    as [record id, acquired, drift start or None]; ``alarm``: the unresolved alarm's id.
    Persistence keeps its last m outcomes (``flags``); the CUSUM its two sums, where each side's
    current run away from zero began (None: at the next record) and its statistic at the last
    record counted (the larger side, before a signal's restart).
    """

    alarm: int | None = None
    after: int | None = None
    through: int | None = None
    quiet: int = 0
    first: list[Any] | None = None
    flags: list[bool] = field(default_factory=list)
    up: float = 0.0
    low: float = 0.0
    up_from: int | None = None
    low_from: int | None = None
    statistic: float = 0.0

    def count(self, fired: bool, at: int, record_id: int, drift: int | None, clear_after: int) -> None:
        """One more record: a firing starts a run, or goes on with the current one if fewer than
        ``clear_after`` records have not fired since the last."""
        self.through = at
        if fired:
            if self.first is None or self.quiet >= clear_after:
                self.first = [record_id, at, drift]
            self.quiet = 0
        else:
            self.quiet += 1


@dataclass
class Kept:
    """Where a structure's rules stand (its ``AlarmState`` row).

    ``rules``: the rules' parameters it was built under (other rules: built again); ``newest``: the
    newest verdict counted, [record id, verdict id, acquired]; ``modes``: the fault modes that
    verdict was judged against (one before any), the CUSUM charts sharing the false alarms;
    ``shares``: the common shares of σ̂k² of the newest ``WINDOW`` healthy verdicts (of all
    verdicts, until one is healthy: ``healthy``), whose median the CUSUM is designed for; and a
    :class:`Track` per rule kind and fault mode (``"cusum k2"``, ``"persistence"``). Of the newest
    verdict, the modes whose CUSUM it did not step: ``pinned`` (k̂ at its model's range limit) and
    ``misfit`` (:func:`_misfits`; ``localised`` the mode its fault was localised to).
    """

    rules: list[dict[str, Any]]
    newest: list[int] | None = None
    modes: int = 1
    shares: list[float] = field(default_factory=list)
    healthy: bool = False
    tracks: dict[str, Track] = field(default_factory=dict)
    pinned: dict[str, float] = field(default_factory=dict)
    misfit: list[str] = field(default_factory=list)
    localised: str | None = None

    def share(self) -> float:
        """The median of ``shares``: the models' error grows away from the healthy state, and a
        design for the healthy structure must not move because a fault is under way."""
        return float(statistics.median(self.shares)) if self.shares else 0.0  # numpy's costs more on a list

    def dumps(self) -> str:
        document = vars(self) | {"tracks": {key: vars(track) for key, track in self.tracks.items()}}
        return json.dumps(document, separators=(",", ":"))

    @classmethod
    def loads(cls, text: str) -> Kept:
        document = json.loads(text)
        document["tracks"] = {key: Track(**track) for key, track in document["tracks"].items()}
        return cls(**document)


def _key(kind: str, mode: str | None) -> str:
    return kind if mode is None else f"{kind} {mode}"


def _microseconds(at: dt.datetime) -> int:
    return (at - EPOCH) // MICROSECOND


def _moment(at: int) -> dt.datetime:
    return EPOCH + dt.timedelta(microseconds=at)


EPOCH = dt.datetime(1970, 1, 1, tzinfo=dt.UTC)
MICROSECOND = dt.timedelta(microseconds=1)


def _fingerprint(rules: list[AlarmRule]) -> list[dict[str, Any]]:
    return [rule.model_dump(mode="json") for rule in rules]


def _step(kept: Kept, rules: list[AlarmRule], p: Point) -> list[str]:
    """Count the verdict ``p``, newer than every verdict counted, in ``kept``; the keys of the
    tracks that counted it (a rule's track counts only the records acquired after its last
    resolution, a CUSUM's only those judged against its fault mode)."""
    at = _microseconds(p.acquired_at)
    kept.newest = [p.record_id, p.verdict_id, at]
    kept.pinned = {mode: p.modes[mode][0] for mode in sorted(p.pinned & p.modes.keys())}
    misfit = _misfits(p)
    kept.misfit = sorted(misfit)
    kept.localised = p.reference_mode if p.status == "faulty" else None
    if p.modes:
        kept.modes = len(p.modes)
        share = max(rules_math.common_share(sigma, alone) for _, sigma, alone in p.modes.values())
        if p.status == "healthy" and not kept.healthy:
            kept.shares, kept.healthy = [], True
        if p.status == "healthy" or not kept.healthy:
            kept.shares = [*kept.shares[1 - WINDOW :], share] if WINDOW > 1 else [share]
    else:
        kept.modes = 1
    counted: list[str] = []

    def track(kind: str, mode: str | None) -> Track | None:
        key = _key(kind, mode)
        kept_track = kept.tracks.setdefault(key, Track())
        if kept_track.after is not None and at <= kept_track.after:
            return None
        counted.append(key)
        return kept_track

    for rule in rules:
        if isinstance(rule, PersistenceRule):
            if (t := track(rule.kind, None)) is not None:
                t.flags = [*t.flags, p.status in FLAGGED][-rule.m :]
                t.count(sum(t.flags) >= rule.k, at, p.record_id, None, rule.clear_after)
        elif isinstance(rule, SeverityRule):
            known = {key.split(" ", 1)[1] for key in kept.tracks if key.startswith("severity ")}
            for mode in sorted(known | set(p.modes)):
                if (t := track(rule.kind, mode)) is not None:
                    t.count(_severe(p, mode, rule.threshold), at, p.record_id, None, rule.clear_after)
        else:
            try:
                design = cusum_design(rule, kept.modes, kept.share())
            except InputError:  # GET …/alarm-rules and the structure's page say why
                continue
            # A k̂ pinned at the range limit is no z, nor one under a model that misfits the record.
            for mode in sorted(p.modes.keys() - p.pinned - misfit):
                if (t := track(rule.kind, mode)) is not None:
                    _cusum_step(t, p, mode, at, design, rule.clear_after)
    return counted


def _misfits(p: Point) -> set[str]:
    """The modes whose k̂ the verdict ``p`` found estimated under a model that does not describe
    its record: every mode but the one its fault is localised to. Such a k̂ moves with the fault
    whatever mode it is (a loosened k2 moves k1's model's k̂ too), and is no evidence that its own
    mode drifts. An unknown fault prefers no mode, and every mode's chart counts it."""
    return set(p.modes) - {p.reference_mode} if p.status == "faulty" else set()


def _cusum_step(
    t: Track, p: Point, mode: str, at: int, design: rules_math.CusumDesign, clear_after: int
) -> None:
    """The two-sided CUSUM one record on (``models.alarms.cusum_chart``, one step of it): a
    signal restarts both sums from zero, as the design assumes."""
    k_hat, sigma, _ = p.modes[mode]
    z = k_hat / sigma
    r, h = design.reference, design.threshold
    t.up_from = at if t.up_from is None else t.up_from
    t.low_from = at if t.low_from is None else t.low_from
    t.up, t.low = max(0.0, t.up + z - r), max(0.0, t.low - z - r)
    t.statistic = max(t.up, t.low)
    fired = t.up > h or t.low > h
    drift = (t.up_from if t.up > h else t.low_from) if fired else None
    if fired:
        t.up = t.low = 0.0
        t.up_from = t.low_from = None
    else:
        t.up_from = None if t.up == 0.0 else t.up_from
        t.low_from = None if t.low == 0.0 else t.low_from
    t.count(fired, at, p.record_id, drift, clear_after)


def _severe(point: Point, mode: str, threshold: float) -> bool:
    if point.reference_mode != mode or point.interval is None:
        return False
    low, high = point.interval
    return rules_math.severity(low, high, threshold) or rules_math.severity(low, high, -threshold)


def _replay(
    session: Session,
    structure_id: int,
    rules: list[AlarmRule],
    limit: dt.datetime,
    series: dict[str, list[Any]] | None = None,
) -> Kept:
    """Where the rules stand, built from the history: the newest verdict of each of the
    structure's newest ``WINDOW`` records acquired up to ``limit`` counted in order from an empty
    state, each rule's track from the last resolution of its alarm on. ``series`` collects each
    CUSUM track's statistic."""
    kept = Kept(_fingerprint(rules))
    for (kind, mode), through in _resolved_through(session, structure_id).items():
        kept.tracks[_key(kind, mode)] = Track(after=_microseconds(through))
    for (kind, mode), alarm in _unresolved(session, structure_id).items():
        kept.tracks.setdefault(_key(kind, mode), Track()).alarm = alarm.id
    for p in newest_points(session, structure_id, WINDOW, limit):
        counted = _step(kept, rules, p)
        if series is not None:
            for key in counted:
                if key.startswith("cusum "):
                    series.setdefault(key, []).append((p.acquired_at, kept.tracks[key].statistic))
    return kept


def _standing(session: Session, structure_id: int, rules: list[AlarmRule], limit: dt.datetime) -> Kept:
    """The kept state if it is that of these rules, else built from the history (not kept)."""
    text = session.execute(STATE_OF, {"structure_id": structure_id}).scalar_one_or_none()
    kept = Kept.loads(text) if text is not None else None
    return (
        kept
        if kept is not None and kept.rules == _fingerprint(rules)
        else _replay(session, structure_id, rules, limit)
    )


# --- evaluation -------------------------------------------------------------------------------


def evaluate(
    session: Session,
    structure: Structure,
    limit: dt.datetime,
    verdict: Point | None = None,
    new_record: bool = False,
) -> None:
    """Count ``verdict``, just stored, in the structure's kept rule state; open, keep or resolve its
    alarms.

    Called in the transaction that stored the verdict, after its insert (``new_record``: its
    record was stored by the same transaction, so has no other verdict), and when the rules
    change, with none: only flushes. A verdict newer than every one counted, of a record with no
    other verdict, is counted on the kept state: each rule's track one record on. Any other (a
    record uploaded late, a re-inspection, a structure without a kept state or whose rules
    changed, or whose newest counted verdict lies past ``limit``: stored with a date in the future
    before such dates were refused, it would stand for the structure's present) has the state
    rebuilt from the history acquired up to ``limit`` (:func:`_replay`). Every transition is
    announced through :func:`service.domain.notifications.notify`, delivered after the commit.
    """
    lock(session, structure.id)
    rules, _ = rules_of(session, structure.id)
    text = session.execute(STATE_OF, {"structure_id": structure.id}).scalar_one_or_none()
    kept = Kept.loads(text) if text is not None else None
    if (
        verdict is not None
        and kept is not None
        and kept.newest is not None
        and kept.newest[2] <= _microseconds(limit)
        and kept.rules == _fingerprint(rules)
        and _after_newest(verdict, kept.newest)
        and (new_record or session.execute(OTHER_VERDICT, vars(verdict)).first() is None)
    ):
        counted = _step(kept, rules, verdict)
    else:
        kept = _replay(session, structure.id, rules, limit)
        counted = [key for key, track in kept.tracks.items() if track.through is not None]
    _apply(session, structure, rules, kept, counted)
    if text is None:
        session.execute(NEW_STATE, {"structure_id": structure.id, "state": kept.dumps()})
    else:
        session.execute(KEEP_STATE, {"structure": structure.id, "state": kept.dumps()})


def _after_newest(p: Point, newest: list[int]) -> bool:
    record_id, verdict_id, at = newest
    return p.record_id != record_id and (_microseconds(p.acquired_at), p.verdict_id) > (at, verdict_id)


def _apply(
    session: Session, structure: Structure, rules: list[AlarmRule], kept: Kept, counted: list[str]
) -> None:
    """Each counted track's alarm: kept (its ``evaluated_through`` the newest record counted),
    resolved once ``clear_after`` records in a row have not fired (the track then starts again
    from the records acquired later), or opened on the first firing of a current run. Tracks are
    taken in the rules' order, each rule's modes by name, whichever way they were counted: the
    alarms one verdict opens get their ids in one order."""
    by_kind = {rule.kind: rule for rule in rules}
    rank = {rule.kind: index for index, rule in enumerate(rules)}
    through = []
    for key in sorted(counted, key=lambda key: (rank.get(key.partition(" ")[0], len(rank)), key)):
        kind, _, mode = key.partition(" ")
        rule, t = by_kind.get(kind), kept.tracks[key]
        if rule is None or t.through is None:
            continue
        if t.alarm is not None:
            if t.quiet < rule.clear_after:
                through.append({"alarm": t.alarm, "through": _moment(t.through)})
                continue
            alarm = session.get_one(Alarm, t.alarm)
            alarm.evaluated_through = max(alarm.evaluated_through, _moment(t.through))
            _end(session, structure, kept, key, "cleared", None)
        elif t.first is not None and t.quiet < rule.clear_after:
            if isinstance(rule, CusumRule) and _design_refusal(rule, kept) is not None:
                # The chart fired where it ran (a late record, the history replayed) but has
                # stopped since: no alarm opens on a design that is gone (:func:`_stop_cusum`).
                continue
            t.alarm = _open(session, structure, rule, kept, mode or None, t)
    if through:
        session.execute(THROUGH, through)
    _stop_cusum(session, structure, rules, kept)


def _stop_cusum(session: Session, structure: Structure, rules: list[AlarmRule], kept: Kept) -> None:
    """Resolve the CUSUM's unresolved alarms as ``rule_not_running`` when no CUSUM can be designed
    for the structure as it stands (the rules changed, or the models' common error grew): the
    rules' answer says the CUSUM does not run, and no alarm stays open on a chart that stopped.
    The note says why; should a design exist again, the charts count the records acquired later."""
    rule = next((r for r in rules if isinstance(r, CusumRule)), None)
    open_alarms = [key for key, t in kept.tracks.items() if key.startswith("cusum ") and t.alarm is not None]
    if rule is None or not open_alarms:
        return
    refusal = _design_refusal(rule, kept)
    if refusal is not None:
        for key in open_alarms:
            _end(session, structure, kept, key, "rule_not_running", refusal)


def _design_refusal(rule: CusumRule, kept: Kept) -> str | None:
    """Why no CUSUM can be designed for the structure as it stands (:func:`cusum_design`); None
    where one can."""
    try:
        cusum_design(rule, kept.modes, kept.share())
    except InputError as refusal:
        return str(refusal)
    return None


def _end(session: Session, structure: Structure, kept: Kept, key: str, how: str, note: str | None) -> None:
    """Resolve the track's alarm by the service; the track starts again after its last record."""
    alarm = session.get_one(Alarm, kept.tracks[key].alarm)
    _resolve(session, structure, alarm, how, None, note)
    kept.tracks[key] = Track(after=_microseconds(alarm.evaluated_through))


def _open(
    session: Session, structure: Structure, rule: AlarmRule, kept: Kept, mode: str | None, t: Track
) -> int:
    assert t.first is not None and t.through is not None
    record_id, triggered, drift = t.first
    document = rule.model_dump(mode="json")
    if isinstance(rule, CusumRule):
        document["design"] = vars(cusum_design(rule, kept.modes, kept.share())) | {"modes": kept.modes}
    alarm = Alarm(
        structure_id=structure.id,
        organisation_id=structure.organisation_id,
        rule_kind=rule.kind,
        rule=document,
        fault_mode=mode,
        state="open",
        opened_at=utcnow(),
        record_id=record_id,
        triggered_at=_moment(triggered),
        drift_started_at=_moment(drift) if drift is not None else None,
        evaluated_through=_moment(t.through),
    )
    alarm.transitions.append(AlarmTransition(from_state=None, to_state="open", at=alarm.opened_at))
    session.add(alarm)
    session.flush()
    _announce(session, structure, alarm, "alarm.opened")
    return alarm.id


def cusum_series(session: Session, structure_id: int, limit: dt.datetime) -> list[CusumSeries]:
    """Each fault mode's CUSUM statistic over the records the rules look at (the newest
    ``WINDOW`` acquired up to ``limit``, counted from the history as :func:`_replay` counts them),
    with its threshold; none when the structure has no CUSUM rule."""
    rules, _ = rules_of(session, structure_id)
    rule = next((r for r in rules if isinstance(r, CusumRule)), None)
    if rule is None:
        return []
    series: dict[str, list[Any]] = {}
    kept = _replay(session, structure_id, rules, limit, series)
    try:
        threshold = cusum_design(rule, kept.modes, kept.share()).threshold
    except InputError:
        return []
    return [
        CusumSeries(key.split(" ", 1)[1], [at for at, _ in values], [s for _, s in values], threshold)
        for key, values in sorted(series.items())
    ]


def newest_points(session: Session, structure_id: int, count: int, limit: dt.datetime) -> list[Point]:
    """The newest verdict of each of the structure's newest ``count`` inspected records acquired
    up to ``limit``, oldest first (a re-inspection with new models re-judges a record: its earlier
    verdicts are passed over, each through the index on the record), read from its history."""
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
            Verdict.acquired_at <= limit,
            ~exists().where(later.record_id == Verdict.record_id, later.id > Verdict.id),
        )
        .order_by(Verdict.acquired_at.desc(), Verdict.id.desc())
        .limit(count)
    ).all()
    return [point(*row) for row in reversed(rows)]


def _unresolved(session: Session, structure_id: int) -> dict[tuple[str, str | None], Alarm]:
    alarms = session.scalars(UNRESOLVED_OF, {"structure_id": structure_id})
    return {(alarm.rule_kind, alarm.fault_mode): alarm for alarm in alarms}


def _resolved_through(session: Session, structure_id: int) -> dict[tuple[str, str | None], dt.datetime]:
    rows = session.execute(RESOLVED_THROUGH, {"structure_id": structure_id})
    return {(kind, mode): through for kind, mode, through in rows}


def forget_states(session: Session, structure_ids: set[int]) -> None:
    """Drop the kept rule states of structures whose verdicts are about to be deleted (by the
    retention) or whose alarm was resolved by hand, each rebuilt from what is left of its
    history the next time its rules run. The structures are locked first, in order of id, as
    :func:`lock` locks one: no evaluation reads a state, or builds one from a history, that the
    deletion is changing."""
    ordered = sorted(structure_ids)
    session.execute(
        select(Structure.id)
        .where(Structure.id.in_(ordered))
        .order_by(Structure.id)
        .with_for_update(key_share=True)
    )
    session.execute(delete(AlarmState).where(AlarmState.structure_id.in_(ordered)))


def lock(session: Session, structure_id: int) -> None:
    """The structure's row lock (``FOR NO KEY UPDATE``, as trainings take it): evaluations of one
    structure run one after another, each seeing the alarms the previous one committed; uploads,
    whose foreign keys take ``KEY SHARE`` locks, are not held up. SQLite has one writer.

    Taken before the structure's state row (``service.domain.fleet``) by every transaction that
    takes both, so that none waits for the other in a cycle: a stored verdict's alarms, then its
    counts (``inspections.store_verdict``); an upload inspected at once locks it before storing
    its record (``ingest``).

    On SQLite the writer gate is taken here too: a record stored without an acquisition time is
    stamped after it, so records of one structure are stamped in the order their verdicts are
    counted, and concurrent uploads are counted on the kept state rather than each replayed as
    a late record."""
    session.execute(LOCK, {"structure_id": structure_id})
    hold_writer_gate(session)


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
    """Resolve an alarm by hand. Its structure is locked first, as an evaluation locks it, and the
    alarm read again under the lock; the rules' kept state is dropped, to be rebuilt from the
    history, whose rule then counts only the records acquired after the alarm's last evaluation."""
    alarm = _get(session, principal, alarm_id)
    forget_states(session, {alarm.structure_id})
    session.refresh(alarm)
    if alarm.state == "resolved":
        raise ConflictError(f"alarm {alarm_id} is resolved already ({alarm.resolution})")
    structure = get_structure(session, principal, alarm.structure_id)
    _resolve(session, structure, alarm, "by_hand", session.get(ApiKey, principal.key_id), note or None)
    return alarm


def _resolve(
    session: Session, structure: Structure, alarm: Alarm, how: str, key: ApiKey | None, note: str | None
) -> None:
    """``key`` None: the service resolved it (the rule cleared, was removed, or stopped running)."""
    now = utcnow()
    alarm.transitions.append(
        AlarmTransition(from_state=alarm.state, to_state="resolved", at=now, key=key, note=note)
    )
    alarm.state, alarm.resolved_at, alarm.resolved_key = "resolved", now, key
    alarm.resolution, alarm.resolution_note = how, note
    session.flush()
    _announce(session, structure, alarm, "alarm.resolved")


def _announce(session: Session, structure: Structure, alarm: Alarm, event: str) -> None:
    notifications.notify(session, structure.organisation_id, event, alarm_payload(alarm))


# --- reading ----------------------------------------------------------------------------------

LOADED = (
    selectinload(Alarm.acknowledged_key),
    selectinload(Alarm.resolved_key),
)


def _get(session: Session, principal: Principal, alarm_id: int) -> Alarm:
    return get_owned(session, principal, Alarm, alarm_id, "alarm", options=list(LOADED))


def get_alarm(session: Session, principal: Principal, alarm_id: int) -> Alarm:
    """The alarm with its transitions and the keys that made them."""
    return get_owned(
        session,
        principal,
        Alarm,
        alarm_id,
        "alarm",
        options=[*LOADED, selectinload(Alarm.transitions).selectinload(AlarmTransition.key)],
    )


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
) -> Page[Alarm, int]:
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
    return Page(items=page, next_cursor=page[-1].id if len(rows) > limit else None)


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


def alarm_payload(alarm: Alarm) -> dict[str, Any]:
    """The alarm as its notifications carry it: the API's answer for it, as JSON."""
    return AlarmOut.model_validate(alarm, from_attributes=True).model_dump(mode="json")
