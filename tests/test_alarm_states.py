"""The alarm rules' state kept per rule and fault mode, against the same rules counted from the history.

After every verdict each rule's track (a CUSUM's sums, persistence's last m outcomes, the current
run of firings) moves one record on, in the structure's ``alarm_states`` row, without reading the
history; a verdict that is not the newest, or a structure without a kept state, has the state
rebuilt from the history (``alarms._replay``). These tests store verdicts as
``inspections.store_verdict`` does (a row, then ``alarms.evaluate`` with its point) on real
SQLite files, in orders the service meets — records uploaded late, re-inspections, a verdict whose
later sibling was committed first — and check that the kept state is the one the history gives,
and that the alarms opened and resolved are those of the same verdicts counted from the history.
"""

from __future__ import annotations

import datetime as dt
import itertools
from pathlib import Path

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from sqlalchemy import delete, event, insert, select
from sqlalchemy.orm import Session

from harness import migrated
from service.db import make_engine
from service.domain import alarms, fleet
from service.tables import Alarm, AlarmState, Organisation, Record, Structure, Verdict

T0 = dt.datetime(2026, 6, 1, tzinfo=dt.UTC)
HOUR = dt.timedelta(hours=1)
# The latest acquisition that stands for a structure (the server's clock plus the skew): well after
# every record of these tests but the one dated in the future.
PRESENT = T0 + 10_000 * HOUR


def _database(path: Path) -> tuple[Session, Structure]:
    """A new SQLite file at the newest revision (a copy of one migrated once a process) with one
    organisation's structure and its empty alarm state."""
    session = Session(make_engine(migrated.sqlite(path)))
    organisation = Organisation(name="o")
    session.add(organisation)
    session.flush()
    structure = Structure(organisation_id=organisation.id, name="s", fs=1500.0, description="")
    session.add(structure)
    session.flush()
    fleet.open_state(session, structure)
    session.commit()
    return session, structure


def _record(session: Session, structure: Structure, acquired_at: dt.datetime) -> int:
    record = Record(
        structure_id=structure.id, fs=1500.0, n_samples=3, acquired_at=acquired_at,
        sha256=f"{session.scalar(select(Record.id).order_by(Record.id.desc())) or 0:064d}"[-64:],
        x=b"", y=b"",
    )  # fmt: skip
    session.add(record)
    session.flush()
    return record.id


def _insert_verdict(
    session: Session, structure: Structure, record_id: int, status: str, z: dict[str, float], model_set: str
) -> alarms.Point:
    """A verdict's row as the inspection writes it, and its point; not yet evaluated."""
    acquired_at = session.get(Record, record_id).acquired_at
    modes = [
        {"name": name, "k_hat": 0.01 * value, "sigma_k": 0.01, "sigma_k_record": 0.0097}
        for name, value in z.items()
    ]
    faulty = status == "faulty"
    interval = (0.3, 0.4) if faulty else (-0.01, 0.01)
    values = dict(
        record_id=record_id, structure_id=structure.id, acquired_at=acquired_at, model_set=model_set,
        status=status, fault_detected=status != "healthy", fault_mode="k2" if faulty else None,
        reference_mode="k2", interval_low=interval[0], interval_high=interval[1], alpha=0.05, lags=4,
        n_samples=3, z_critical=1.96, q_critical_detection=1.0, detected_by=[], modes=modes,
    )  # fmt: skip
    verdict_id = session.execute(insert(Verdict).returning(Verdict.id), values).scalar_one()
    return alarms.point(verdict_id, record_id, acquired_at, status, "k2", *interval, modes)


def _alarms(session: Session) -> list[tuple]:
    rows = session.execute(
        select(
            Alarm.rule_kind, Alarm.fault_mode, Alarm.state, Alarm.resolution, Alarm.record_id,
            Alarm.triggered_at, Alarm.drift_started_at, Alarm.evaluated_through, Alarm.rule,
        ).order_by(Alarm.id)
    )  # fmt: skip
    return [tuple(row) for row in rows]


def _kept(session: Session, structure: Structure) -> alarms.Kept:
    text = session.scalar(select(AlarmState.state).where(AlarmState.structure_id == structure.id))
    assert text is not None
    return alarms.Kept.loads(text)


def _from_history(session: Session, structure: Structure) -> alarms.Kept:
    return alarms._replay(session, structure.id, alarms.rules_of(session, structure.id)[0], PRESENT)


def _store(session: Session, structure: Structure, hours: float, status: str, z: dict[str, float]) -> None:
    record_id = _record(session, structure, T0 + hours * HOUR)
    point = _insert_verdict(session, structure, record_id, status, z, "a")
    alarms.evaluate(session, structure, PRESENT, point, new_record=True)
    session.commit()


# A step: a new record acquired ``offset`` hours after the first (any order: late uploads), or a
# re-inspection of an earlier record (its index modulo those stored), with a status and z values.
statuses = st.sampled_from(["healthy", "healthy", "faulty", "unknown_fault"])
zs = st.fixed_dictionaries({"k1": st.floats(-6, 6), "k2": st.floats(-3, 9)})
steps = st.lists(
    st.one_of(
        st.tuples(st.just("new"), st.integers(0, 40), statuses, zs),
        st.tuples(st.just("next"), st.integers(1, 3), statuses, zs),
        st.tuples(st.just("again"), st.integers(0, 1000), statuses, zs),
    ),
    min_size=1,
    max_size=40,
)


# A faulty verdict localised to k2 starts k2's CUSUM before k1's (k1 misfits it); a later verdict
# opens both charts' alarms at once: their ids in one order, whether counted on the kept state or
# on the history rebuilt.
TWO_CHARTS_AT_ONCE = [
    ("new", 0, "faulty", {"k1": 0.0, "k2": 0.0}),
    *[("new", 0, "healthy", {"k1": 0.0, "k2": 0.0})] * 2,
    ("new", 0, "healthy", {"k1": 6.0, "k2": 6.0}),
]


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(plan=steps)
@example(plan=TWO_CHARTS_AT_ONCE)
def test_the_kept_state_gives_the_alarms_the_history_gives(plan, tmp_path_factory):
    """Two databases receive the same verdicts: one keeps its rules' state, the other has it
    dropped before every evaluation, so that its rules count the history again each time. After
    each verdict the kept state is the history's, and both have the same alarms. Records arrive
    in order (``next``: after the newest, the common case, counted on the kept state) and out of
    it (``new``: anywhere, often late), and are inspected again (``again``)."""
    folder = tmp_path_factory.mktemp("states")
    kept, structure = _database(folder / "kept.db")
    history, other = _database(folder / "history.db")
    records: list[int] = []  # the same ids in both databases
    newest = 0
    for index, (kind, value, status, z) in enumerate(plan):
        again = kind == "again" and records
        hours = newest + value if kind == "next" else value if kind == "new" else 0
        newest = max(newest, hours)
        for session, target in ((kept, structure), (history, other)):
            if again:
                record_id = records[value % len(records)]
            else:
                record_id = _record(session, target, T0 + hours * HOUR)
            point = _insert_verdict(session, target, record_id, status, z, f"set{index}")
            if session is history:
                session.execute(delete(AlarmState))
            alarms.evaluate(session, target, PRESENT, point, new_record=not again)
            session.commit()
        if not again:
            records.append(record_id)
        assert _kept(kept, structure) == _from_history(kept, structure)
        assert _alarms(kept) == _alarms(history)


def test_a_verdict_newer_than_every_one_counted_is_counted_without_reading_the_history(tmp_path):
    """The upload's path: the rules' state read and written back, the rules read, and nothing of
    the verdicts, however many the structure has; its alarm's newest record moved on in one
    statement."""
    session, structure = _database(tmp_path / "s.db")
    for hours in range(30):
        _store(session, structure, hours, "faulty" if hours % 2 else "healthy", {"k2": 0.3})
    assert [row[0] for row in _alarms(session)] == ["persistence"]
    statements: list[str] = []
    engine = session.get_bind()
    event.listen(engine, "before_cursor_execute", lambda *args: statements.append(args[2]))
    record_id = _record(session, structure, T0 + 40 * HOUR)
    point = _insert_verdict(session, structure, record_id, "faulty", {"k2": 0.3}, "a")
    statements.clear()
    alarms.evaluate(session, structure, PRESENT, point, new_record=True)
    session.commit()
    assert [s for s in statements if "verdicts" in s] == [] and len(statements) <= 6, statements
    assert _kept(session, structure) == _from_history(session, structure)
    assert _alarms(session)[0][7] == T0 + 40 * HOUR  # evaluated_through


def test_a_verdict_whose_record_has_a_later_one_counted_changes_nothing(tmp_path):
    """Two inspections of one record run concurrently and the later one (by id) commits first: the
    earlier, evaluated second, is not that record's newest verdict and must not be counted."""
    session, structure = _database(tmp_path / "s.db")
    record_id = _record(session, structure, T0)
    first = _insert_verdict(session, structure, record_id, "healthy", {"k2": 0.1}, "a")
    second = _insert_verdict(session, structure, record_id, "faulty", {"k2": 5.0}, "b")
    alarms.evaluate(session, structure, PRESENT, second)
    alarms.evaluate(session, structure, PRESENT, first)
    session.commit()
    state = _kept(session, structure)
    assert state.newest is not None and state.newest[1] == second.verdict_id
    assert state.tracks["persistence"].flags == [True]
    assert state == _from_history(session, structure)


def test_a_record_uploaded_late_is_counted_in_its_place(tmp_path):
    """A record acquired before the newest counted is counted where it belongs: persistence's 3 of
    5 holds once the late faulty record fills the gap between two faulty ones."""
    session, structure = _database(tmp_path / "s.db")
    for hours, status in ((10, "faulty"), (30, "faulty"), (40, "healthy")):
        _store(session, structure, hours, status, {})
    assert _alarms(session) == []
    _store(session, structure, 20, "faulty", {})
    state = _kept(session, structure)
    assert state.tracks["persistence"].flags == [True, True, True, False]
    assert state.newest is not None and state.newest[2] == alarms._microseconds(T0 + 40 * HOUR)
    assert state == _from_history(session, structure)
    assert [(row[0], row[5]) for row in _alarms(session)] == [("persistence", T0 + 30 * HOUR)]


def test_the_retention_s_deletions_drop_the_state_which_the_history_then_rebuilds(tmp_path):
    session, structure = _database(tmp_path / "s.db")
    for hours, status in zip(range(6), itertools.cycle(["faulty", "healthy"]), strict=False):
        _store(session, structure, hours, status, {})
    alarms.forget_states(session, {structure.id})
    session.execute(delete(Verdict).where(Verdict.acquired_at < T0 + 3 * HOUR))
    assert session.scalar(select(AlarmState.state)) is None
    _store(session, structure, 9, "faulty", {})
    assert _kept(session, structure).tracks["persistence"].flags == [False, True, False, True]
    assert _kept(session, structure) == _from_history(session, structure)


def test_the_cusum_runs_on_past_the_records_the_history_is_rebuilt_from(tmp_path, monkeypatch):
    """A small drift, each z above the reference but far below the threshold, builds the CUSUM up
    over more records than a rebuild reads (``WINDOW``, shortened here): the running chart signals
    and dates the drift to its first record, where a chart restarted at the edge of the newest
    ``WINDOW`` records would never reach the threshold."""
    monkeypatch.setattr(alarms, "WINDOW", 4)
    session, structure = _database(tmp_path / "s.db")
    for hours in range(40):
        _store(session, structure, hours, "healthy", {"k2": 1.8})
        if _alarms(session):
            break
    (cusum,) = [row for row in _alarms(session) if row[0] == "cusum"]
    threshold = cusum[8]["design"]["threshold"]
    assert hours + 1 > 4 and (hours + 1) * (1.8 - 1.0) > threshold
    assert cusum[6] == T0  # the drift began with the first record
    assert _from_history(session, structure).tracks["cusum k2"].statistic < threshold


@pytest.mark.parametrize("size", [0, 1, 5, 40])
def test_persistence_in_one_pass_is_persistence_after_each_verdict(size):
    from models.alarms import persistence, persistence_path

    for seed in range(20):
        flags = [(seed * 7919 + i * i * 31) % 5 < 2 for i in range(size)]
        for k, m in ((1, 1), (2, 3), (3, 5), (5, 5)):
            assert persistence_path(flags, k, m) == [persistence(flags[: i + 1], k, m) for i in range(size)]


def test_a_verdict_dated_in_the_future_never_stands_for_the_present(tmp_path):
    """A healthy verdict stored with a date in the future (before such dates were refused) was the
    newest counted: the faults acquired since are not late records behind it, and it counts as no
    quiet record that would clear their alarm."""
    session, structure = _database(tmp_path / "s.db")
    record_id = _record(session, structure, dt.datetime(9999, 12, 31, tzinfo=dt.UTC))
    future = _insert_verdict(session, structure, record_id, "healthy", {"k2": 0.1}, "a")
    alarms.evaluate(session, structure, dt.datetime.max.replace(tzinfo=dt.UTC), future, new_record=True)
    session.commit()
    for hours in range(4):
        _store(session, structure, hours, "faulty", {"k2": 5.0})
    state = _kept(session, structure)
    assert state.newest is not None and state.newest[0] != record_id
    assert state.tracks["persistence"].flags == [True] * 4
    opened = [(row[0], row[2], row[4]) for row in _alarms(session)]
    assert {kind for kind, state, _ in opened if state == "open"} == {"cusum", "persistence"}
    assert record_id not in {trigger for _, _, trigger in opened}
    assert state == _from_history(session, structure)


def test_a_chart_that_fired_where_it_ran_opens_no_alarm_once_its_design_is_gone(tmp_path):
    """A record uploaded late (the history replayed) can fire a fault mode's CUSUM at its place,
    where the models' common error still allowed a design, while the records after it raised that
    error beyond any: the chart stopped there, and the verdict is counted without an alarm opened
    on a design that no longer exists, as the rules' answer says the CUSUM does not run."""
    session, structure = _database(tmp_path / "s.db")

    def store(hours: float, z: float, sigma_k_record: float) -> None:
        record_id = _record(session, structure, T0 + hours * HOUR)
        point = _insert_verdict(session, structure, record_id, "healthy", {"k2": z}, "a")
        verdict = session.get_one(Verdict, point.verdict_id)
        verdict.modes = [{**mode, "sigma_k_record": sigma_k_record} for mode in verdict.modes]
        session.flush()
        point = alarms.point(
            point.verdict_id, record_id, point.acquired_at, "healthy", "k2", -0.01, 0.01, verdict.modes
        )
        alarms.evaluate(session, structure, PRESENT, point, new_record=True)
        session.commit()

    for hour in range(3):
        store(hour, 0.0, 0.0097)  # a common share of 6 %: a design exists
    for hour in range(10, 20):
        store(hour, 0.0, 0.005)  # 75 %: none does
    store(5, 60.0, 0.0097)  # late: at its place the median share is still 6 %, and k2's chart fires
    assert [row for row in _alarms(session) if row[0] == "cusum"] == []
    assert _kept(session, structure) == _from_history(session, structure)
