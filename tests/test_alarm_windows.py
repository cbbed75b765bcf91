"""The window of verdicts the alarm rules run over, kept on write, against the history read again.

After every verdict the rules run over the newest verdict of each of the structure's newest
``WINDOW`` records. They used to read those from the history; they now read the structure's
``alarm_windows`` row, which each verdict's transaction updates. These tests store verdicts as
``inspections.store_verdict`` does (a row, then ``alarms.evaluate`` with its point) on real
SQLite files, in orders the service meets — records uploaded late, re-inspections, a verdict whose
later sibling was committed first — and check that the kept window is the one the history gives,
and that the alarms opened and resolved are those of the same verdicts judged from the history.
The window is shortened (``WINDOW``, a parameter of the rules) so that it fills and slides within
a few dozen verdicts.
"""

from __future__ import annotations

import datetime as dt
import itertools
import shutil
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sqlalchemy import delete, insert, select
from sqlalchemy.orm import Session

from service.db import make_engine
from service.domain import alarms, fleet
from service.migrate import upgrade_database
from service.tables import Alarm, AlarmWindow, Organisation, Record, Structure, Verdict

T0 = dt.datetime(2026, 6, 1, tzinfo=dt.UTC)
HOUR = dt.timedelta(hours=1)
SHORT_WINDOW = 12


@pytest.fixture(scope="module")
def migrated(tmp_path_factory) -> Path:
    """An empty database at the newest revision, copied for each test: migrating is slow."""
    path = tmp_path_factory.mktemp("template") / "empty.db"
    upgrade_database(f"sqlite:///{path}")
    return path


def _database(template: Path, path: Path) -> tuple[Session, Structure]:
    shutil.copyfile(template, path)
    session = Session(make_engine(f"sqlite:///{path}"))
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


def _kept(session: Session, structure: Structure) -> list[alarms.Point]:
    assert session.scalar(select(AlarmWindow.points).where(AlarmWindow.structure_id == structure.id))
    return alarms.window(session, structure.id)


# A step: a new record acquired ``offset`` hours after the first (any order: late uploads), or a
# re-inspection of an earlier record (its index modulo those stored), with a status and z values.
statuses = st.sampled_from(["healthy", "healthy", "faulty", "unknown_fault"])
zs = st.fixed_dictionaries({"k1": st.floats(-6, 6), "k2": st.floats(-3, 9)})
steps = st.lists(
    st.one_of(
        st.tuples(st.just("new"), st.integers(0, 40), statuses, zs),
        st.tuples(st.just("again"), st.integers(0, 1000), statuses, zs),
    ),
    min_size=1,
    max_size=40,
)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(plan=steps)
def test_the_kept_window_gives_the_alarms_the_history_gives(plan, migrated, tmp_path_factory, monkeypatch):
    """Two databases receive the same verdicts: one keeps its window, the other has it dropped
    before every evaluation, so that its rules read the history as they did before the window was
    kept. After each verdict the kept window is the history's, and both have the same alarms."""
    monkeypatch.setattr(alarms, "WINDOW", SHORT_WINDOW)
    folder = tmp_path_factory.mktemp("windows")
    kept, structure = _database(migrated, folder / "kept.db")
    history, other = _database(migrated, folder / "history.db")
    records: list[int] = []  # the same ids in both databases
    for index, (kind, value, status, z) in enumerate(plan):
        again = kind == "again" and records
        for session, target in ((kept, structure), (history, other)):
            if again:
                record_id = records[value % len(records)]
            else:
                record_id = _record(session, target, T0 + (value if kind == "new" else 0) * HOUR)
            point = _insert_verdict(session, target, record_id, status, z, f"set{index}")
            if session is history:
                session.execute(delete(AlarmWindow))
            alarms.evaluate(session, target, point)
            session.commit()
        if not again:
            records.append(record_id)
        assert _kept(kept, structure) == alarms.newest_points(kept, structure.id, SHORT_WINDOW)
        assert _alarms(kept) == _alarms(history)


def test_a_verdict_whose_record_has_a_later_one_kept_leaves_the_window_as_it_is(
    migrated, tmp_path, monkeypatch
):
    """Two inspections of one record run concurrently and the later one (by id) commits first: the
    earlier, evaluated second, is not that record's newest verdict and must not replace it."""
    monkeypatch.setattr(alarms, "WINDOW", SHORT_WINDOW)
    session, structure = _database(migrated, tmp_path / "w.db")
    record_id = _record(session, structure, T0)
    first = _insert_verdict(session, structure, record_id, "healthy", {"k2": 0.1}, "a")
    second = _insert_verdict(session, structure, record_id, "faulty", {"k2": 5.0}, "b")
    alarms.evaluate(session, structure, second)
    alarms.evaluate(session, structure, first)
    session.commit()
    assert [p.verdict_id for p in _kept(session, structure)] == [second.verdict_id]
    assert _kept(session, structure) == alarms.newest_points(session, structure.id, SHORT_WINDOW)


def test_a_record_uploaded_late_takes_its_place_by_acquisition_or_none_in_a_full_window(
    migrated, tmp_path, monkeypatch
):
    monkeypatch.setattr(alarms, "WINDOW", 4)
    session, structure = _database(migrated, tmp_path / "w.db")
    for hours in (10, 20, 30, 40):
        point = _insert_verdict(
            session, structure, _record(session, structure, T0 + hours * HOUR), "healthy", {}, "a"
        )
        alarms.evaluate(session, structure, point)
    for hours, expected in ((25, [20, 25, 30, 40]), (5, [20, 25, 30, 40]), (45, [25, 30, 40, 45])):
        point = _insert_verdict(
            session, structure, _record(session, structure, T0 + hours * HOUR), "faulty", {}, "a"
        )
        alarms.evaluate(session, structure, point)
        session.commit()
        window = _kept(session, structure)
        assert [(p.acquired_at - T0) / HOUR for p in window] == expected
        assert window == alarms.newest_points(session, structure.id, 4)


def test_the_retention_s_deletions_drop_the_window_which_the_history_then_rebuilds(
    migrated, tmp_path, monkeypatch
):
    monkeypatch.setattr(alarms, "WINDOW", SHORT_WINDOW)
    session, structure = _database(migrated, tmp_path / "w.db")
    for hours, status in zip(range(6), itertools.cycle(["faulty", "healthy"]), strict=False):
        point = _insert_verdict(
            session, structure, _record(session, structure, T0 + hours * HOUR), status, {}, "a"
        )
        alarms.evaluate(session, structure, point)
    session.commit()
    alarms.forget_windows(session, {structure.id})
    session.execute(delete(Verdict).where(Verdict.acquired_at < T0 + 3 * HOUR))
    assert session.scalar(select(AlarmWindow.points)) is None
    point = _insert_verdict(session, structure, _record(session, structure, T0 + 9 * HOUR), "faulty", {}, "a")
    alarms.evaluate(session, structure, point)
    session.commit()
    window = _kept(session, structure)
    assert [(p.acquired_at - T0) / HOUR for p in window] == [3, 4, 5, 9]
    assert window == alarms.newest_points(session, structure.id, SHORT_WINDOW)


@pytest.mark.parametrize("size", [0, 1, 5, 40])
def test_persistence_in_one_pass_is_persistence_after_each_verdict(size):
    from models.alarms import persistence, persistence_path

    for seed in range(20):
        flags = [(seed * 7919 + i * i * 31) % 5 < 2 for i in range(size)]
        for k, m in ((1, 1), (2, 3), (3, 5), (5, 5)):
            assert persistence_path(flags, k, m) == [persistence(flags[: i + 1], k, m) for i in range(size)]
