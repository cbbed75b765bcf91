"""The Alembic migrations build exactly the schema the code declares, on both databases."""

from __future__ import annotations

import datetime as dt
import json
import uuid

import pytest
from alembic import command
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from cryptography.fernet import Fernet
from sqlalchemy import JSON, Connection, column, inspect, select, table, text
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service import tables
from service.db import Base, make_engine
from service.migrate import alembic_config, is_ours, upgrade_database
from service.tables import utcnow

# structure_states as the schema before 0024 has it, without the declared table's default count of
# anomalies, which an insert would name.
STATES_BEFORE_0024 = table(
    "structure_states",
    *(
        column(name)
        for name in (
            "structure_id", "organisation_id", "status", "since", "latest_verdict_id", "latest_acquired_at",
            "records", "healthy", "faulty", "unknown_fault",
        )
    ),
)  # fmt: skip


@pytest.fixture(params=["sqlite", "postgresql"])
def fresh_url(request, tmp_path):
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'm.db'}"
    from harness import postgres

    return postgres.create_database(request.getfixturevalue("postgres_url"), f"migrations_{uuid.uuid4().hex}")


def test_upgrade_matches_the_declared_tables(fresh_url):
    upgrade_database(fresh_url)
    engine = make_engine(fresh_url)
    with engine.connect() as connection:
        differences = compare_metadata(
            MigrationContext.configure(connection, opts={"include_name": is_ours}), Base.metadata
        )
        tables_present = set(inspect(connection).get_table_names())
    engine.dispose()
    assert differences == []
    assert set(Base.metadata.tables) <= tables_present


def schema_and_revision(url: str) -> tuple[dict, list]:
    """Every table's columns, indexes, unique and foreign keys, and the Alembic revision stored."""
    engine = make_engine(url)
    with engine.connect() as connection:
        inspector = inspect(connection)
        schema = {
            table: {
                "columns": [(c["name"], str(c["type"]), c["nullable"]) for c in inspector.get_columns(table)],
                "indexes": sorted(
                    (i["name"] or "", tuple(i["column_names"]), bool(i["unique"]))
                    for i in inspector.get_indexes(table)
                ),
                "unique": sorted(tuple(u["column_names"]) for u in inspector.get_unique_constraints(table)),
                "foreign_keys": sorted(
                    (tuple(f["constrained_columns"]), f["referred_table"])
                    for f in inspector.get_foreign_keys(table)
                ),
            }
            for table in inspector.get_table_names()
        }
        revision = [row[0] for row in connection.execute(text("SELECT version_num FROM alembic_version"))]
    engine.dispose()
    return schema, revision


def test_upgrade_is_idempotent(fresh_url):
    """A second upgrade (every `narxwatch` start runs one) changes neither the schema nor the data."""
    upgrade_database(fresh_url)
    schema, revision = schema_and_revision(fresh_url)
    assert set(Base.metadata.tables) <= set(schema)
    assert len(revision) == 1
    engine = make_engine(fresh_url)
    with engine.begin() as connection:
        connection.execute(tables.Organisation.__table__.insert().values(name="kept", created_at=utcnow()))
    engine.dispose()

    upgrade_database(fresh_url)

    assert schema_and_revision(fresh_url) == (schema, revision)
    engine = make_engine(fresh_url)
    with engine.connect() as connection:
        names = connection.execute(select(tables.Organisation.name)).scalars().all()
    engine.dispose()
    assert names == ["kept"]


def _organisation_and_structure(connection: Connection, now: dt.datetime) -> None:
    """Organisation 1 and its structure 1, as the schema of any revision holds them."""
    connection.execute(
        text("INSERT INTO organisations (id, name, created_at) VALUES (1, 'o', :t)"), {"t": now}
    )
    connection.execute(
        text(
            "INSERT INTO structures (id, organisation_id, name, fs, description, created_at) "
            "VALUES (1, 1, 's', 1500.0, '', :t)"
        ),
        {"t": now},
    )


def test_0006_keeps_the_newest_of_two_active_versions(fresh_url):
    """A database left with two active versions of one name (before 0006) keeps only the newest
    active, and from then on the database refuses a second active version."""
    upgrade_database(fresh_url, "0005")
    engine = make_engine(fresh_url)
    versions = Base.metadata.tables["model_versions"]
    now = dt.datetime.now(dt.UTC)
    with engine.begin() as connection:
        _organisation_and_structure(connection, now)
        rows = [("k2", 1, True), ("k2", 2, True), ("k2", 3, False), ("k1", 1, True), ("k1", 2, False)]
        for name, number, active in rows:
            connection.execute(
                versions.insert().values(
                    structure_id=1,
                    kind="fault_mode",
                    name=name,
                    version=number,
                    document={},
                    training={},
                    statistics={},
                    active=active,
                    created_at=now,
                )
            )
    upgrade_database(fresh_url)
    with engine.begin() as connection:
        active = connection.execute(
            select(versions.c.name, versions.c.version).where(versions.c.active)
        ).all()
    assert sorted(active) == [("k1", 1), ("k2", 2)]
    with pytest.raises(IntegrityError), engine.begin() as connection:
        connection.execute(
            versions.update().where(versions.c.name == "k2", versions.c.version == 3).values(active=True)
        )
    engine.dispose()


def test_0008_lists_each_earlier_refinement_s_record_as_fitted(fresh_url):
    """A refinement stored before 0008 was fitted on its one record: after the upgrade it lists
    that record as its only estimation record, and none judged whole."""
    upgrade_database(fresh_url, "0007")
    engine = make_engine(fresh_url)
    now = dt.datetime.now(dt.UTC)
    with engine.begin() as connection:
        _organisation_and_structure(connection, now)
        records = Base.metadata.tables["records"]
        for record_id in (7, 8):
            connection.execute(
                records.insert().values(
                    id=record_id, structure_id=1, fs=1500.0, n_samples=3, acquired_at=now, created_at=now,
                    sha256=f"{record_id:064d}", x=b"", y=b"",
                )
            )  # fmt: skip
        connection.execute(
            Base.metadata.tables["model_versions"]
            .insert()
            .values(
                id=1, structure_id=1, kind="baseline", name="baseline", version=1, document={}, training={},
                statistics={}, active=True, created_at=now,
            )
        )  # fmt: skip
        refinements = Base.metadata.tables["refinements"]
        for refinement_id, record_id in ((1, 8), (2, 7)):
            connection.execute(
                refinements.insert().values(
                    id=refinement_id, structure_id=1, record_id=record_id, base_model_id=1, report={},
                    created_at=now,
                )
            )  # fmt: skip
    upgrade_database(fresh_url)
    with engine.connect() as connection:
        rows = connection.execute(
            text(
                "SELECT refinement_id, record_id, role, position FROM refinement_records "
                "ORDER BY refinement_id"
            )
        ).all()
    assert [tuple(row) for row in rows] == [(1, 8, "estimation", 0), (2, 7, "estimation", 0)]
    with Session(engine) as session:
        refinement = session.get(tables.Refinement, 1)
        assert refinement is not None
        assert refinement.record_ids_of("estimation") == [8] and refinement.record_ids_of("test") == []
    engine.dispose()


def test_0012_fills_each_structure_s_state_and_the_job_counts_from_what_is_stored(fresh_url):
    """Structures stored before 0012 get their state from their history: the newest verdict (by
    acquisition, then id, whatever the order of the ids), the start of its status's last run,
    and their counts; the embedded jobs that ended are counted by state. Downgrading drops both."""
    upgrade_database(fresh_url, "0010")
    engine = make_engine(fresh_url)
    now = dt.datetime.now(dt.UTC)
    day = dt.timedelta(days=1)
    t0 = dt.datetime(2026, 6, 1, tzinfo=dt.UTC)
    table = Base.metadata.tables
    # Verdicts of structure 1 as (id, acquisition day, status), stored in this order of ids:
    # by acquisition they read healthy (2), faulty (3), healthy (4), faulty (1, 5 at one instant), faulty (6).
    history = [(1, 5, "faulty"), (2, 1, "healthy"), (3, 3, "faulty"), (4, 4, "healthy"), (5, 5, "faulty")]
    history.append((6, 6, "faulty"))
    with engine.begin() as connection:
        connection.execute(table["organisations"].insert().values(id=1, name="o", created_at=now))
        for structure_id in (1, 2, 3):
            connection.execute(
                table["structures"].insert().values(
                    id=structure_id, organisation_id=1, name=f"s{structure_id}", fs=1500.0, description="",
                    created_at=now,
                )
            )  # fmt: skip
        for record_id, structure_id in [(n, 1) for n in range(1, 8)] + [(8, 2), (9, 2)]:
            connection.execute(
                table["records"].insert().values(
                    id=record_id, structure_id=structure_id, fs=1500.0, n_samples=3, acquired_at=now,
                    created_at=now, sha256=f"{record_id:064d}", x=b"", y=b"",
                )
            )  # fmt: skip
        for verdict_id, acquired, status in history:
            connection.execute(
                table["verdicts"].insert().values(
                    id=verdict_id, record_id=verdict_id, structure_id=1, acquired_at=t0 + acquired * day,
                    created_at=now, model_set="1", status=status, fault_detected=status != "healthy",
                    alpha=0.05, lags=4, n_samples=3, z_critical=1.96, q_critical_detection=1.0,
                    detected_by=[], modes=[],
                )
            )  # fmt: skip
        for status in ("done", "done", "done", "failed", "queued", "running"):
            connection.execute(
                table["jobs"].insert().values(
                    organisation_id=1, task="inspect_record", args={}, status=status, attempts=1,
                    run_after=now, created_at=now,
                )
            )  # fmt: skip
    upgrade_database(fresh_url)
    with Session(engine) as session:
        states = {s.structure_id: s for s in session.scalars(select(tables.StructureState))}
        counts = dict(session.execute(select(tables.JobCount.state, tables.JobCount.count)).all())
    assert set(states) == {1, 2, 3}
    ordered = [states[structure_id] for structure_id in (1, 2, 3)]
    standing = [(s.status, s.since, s.latest_verdict_id, s.latest_acquired_at) for s in ordered]
    assert standing == [("faulty", t0 + 5 * day, 6, t0 + 6 * day), (None, None, None, None), (None,) * 4]
    tallies = [(s.records, s.healthy, s.faulty, s.unknown_fault) for s in ordered]
    assert tallies == [(7, 2, 4, 0), (2, 0, 0, 0), (0, 0, 0, 0)]
    assert all(s.organisation_id == 1 for s in ordered)
    assert counts == {"done": 3, "failed": 1}

    command.downgrade(alembic_config(fresh_url), "0010")
    with engine.connect() as connection:
        left = set(inspect(connection).get_table_names())
    engine.dispose()
    assert not {"structure_states", "job_counts"} & left and {"structures", "jobs"} <= left


def _structure_with_records(url: str, *channels: object) -> None:
    """An organisation, a structure and a record of each ``channels`` (None: one response), as
    the service stores them."""
    engine = make_engine(url)
    now = utcnow()
    with engine.begin() as connection:
        _organisation_and_structure(connection, now)
        for number, names in enumerate(channels):
            connection.execute(
                tables.Record.__table__.insert().values(
                    structure_id=1, fs=1500.0, n_samples=2, acquired_at=now, created_at=now,
                    sha256=f"{number:064d}", x=b"", y=b"", channels=names,
                )
            )  # fmt: skip
    engine.dispose()


def _channels(url: str) -> list[tuple[object, bool]]:
    engine = make_engine(url)
    with engine.connect() as connection:
        stored = connection.execute(text("SELECT channels, channels IS NULL FROM records ORDER BY id")).all()
    engine.dispose()
    return [(names, bool(null)) for names, null in stored]


def downgraded_once_deleted(url: str, revision: str, refused: str, delete: str) -> None:
    """Downgrading to ``revision`` is refused with a message matching ``refused`` and changes
    nothing; once the rows the ``delete`` statement removes are gone, it goes through."""
    before = schema_and_revision(url)
    with pytest.raises(RuntimeError, match=refused):
        command.downgrade(alembic_config(url), revision)
    assert schema_and_revision(url) == before
    engine = make_engine(url)
    with engine.begin() as connection:
        connection.execute(text(delete))
    engine.dispose()
    command.downgrade(alembic_config(url), revision)
    assert schema_and_revision(url)[1] == [revision]


def test_0015_is_undone_only_once_no_record_of_several_channels_is_stored(fresh_url):
    """Downgrading past 0015 drops the channels the older schema cannot hold: refused, naming how
    many records, while any is stored (and nothing changes); once they are deleted it goes
    through and the records of one response stay. (It used to count every record, JSON's null
    stored for a record of one response being no SQL NULL.)"""
    upgrade_database(fresh_url)
    _structure_with_records(fresh_url, None, ["a1", "a2"], None)
    assert [null for _, null in _channels(fresh_url)] == [True, False, True]
    refused = r"^1 record\(s\) of several channels are stored"
    downgraded_once_deleted(fresh_url, "0014", refused, "DELETE FROM records WHERE channels IS NOT NULL")
    engine = make_engine(fresh_url)
    with engine.connect() as connection:
        assert connection.execute(text("SELECT COUNT(*) FROM records")).scalar() == 2
    engine.dispose()


def test_0017_stores_a_record_of_one_response_with_sql_null_channels(fresh_url):
    """Records stored before 0017 held JSON's null; after it, SQL NULL, as new ones are stored."""
    upgrade_database(fresh_url, "0016")
    _structure_with_records(fresh_url, JSON.NULL, ["a1", "a2"])  # JSON.NULL: what None was stored as
    assert [null for _, null in _channels(fresh_url)] == [False, False]
    upgrade_database(fresh_url)
    assert [null for _, null in _channels(fresh_url)] == [True, False]


def test_0019_gives_each_alarm_the_organisation_of_its_structure_and_undoes_cleanly(fresh_url):
    upgrade_database(fresh_url, "0018")
    engine = make_engine(fresh_url)
    now = dt.datetime.now(dt.UTC)
    with engine.begin() as connection:
        for organisation in (1, 2):
            connection.execute(text("INSERT INTO organisations (id, name, created_at) VALUES (:i, :n, :t)"),
                               dict(i=organisation, n=f"o{organisation}", t=now))  # fmt: skip
        for structure, organisation in ((1, 1), (2, 2), (3, 2)):
            connection.execute(
                text("INSERT INTO structures (id, organisation_id, name, fs, description, created_at) "
                     "VALUES (:s, :o, :n, 1500, '', :t)"),
                dict(s=structure, o=organisation, n=f"s{structure}", t=now),
            )  # fmt: skip
        for alarm, structure in ((1, 3), (2, 1), (3, 2)):
            connection.execute(
                text("INSERT INTO alarms (id, structure_id, rule_kind, rule, state, opened_at, triggered_at, "
                     "evaluated_through) VALUES (:a, :s, 'persistence', '{}', 'open', :t, :t, :t)"),
                dict(a=alarm, s=structure, t=now),
            )  # fmt: skip
        connection.execute(
            text("INSERT INTO alarm_transitions (alarm_id, to_state, at) VALUES (1, 'open', :t)"), dict(t=now)
        )
    engine.dispose()
    upgrade_database(fresh_url)
    engine = make_engine(fresh_url)
    with engine.connect() as connection:
        rows = connection.execute(text("SELECT id, organisation_id FROM alarms ORDER BY id")).all()
        assert rows == [(1, 2), (2, 1), (3, 2)]
        assert connection.execute(text("SELECT alarm_id FROM alarm_transitions")).scalar_one() == 1
    engine.dispose()
    command.downgrade(alembic_config(fresh_url), "0018")
    engine = make_engine(fresh_url)
    with engine.connect() as connection:
        assert "organisation_id" not in {c["name"] for c in inspect(connection).get_columns("alarms")}
        assert connection.execute(text("SELECT COUNT(*) FROM alarms")).scalar() == 3
    engine.dispose()


def test_rebuilding_a_table_on_sqlite_keeps_the_rows_that_refer_to_it(fresh_url):
    """0013 alters verdicts, which SQLite does by copying the table, dropping the old one and
    renaming the copy. With foreign keys enforced during the drop, every verdict's link to its
    models (ON DELETE CASCADE) was deleted and each structure's latest verdict (ON DELETE SET NULL)
    forgotten; the migrations run with them off and check the references afterwards."""
    upgrade_database(fresh_url, "0012")
    engine = make_engine(fresh_url)
    now = dt.datetime.now(dt.UTC)
    table = Base.metadata.tables
    with engine.begin() as connection:
        connection.execute(table["organisations"].insert().values(id=1, name="o", created_at=now))
        connection.execute(
            table["structures"]
            .insert()
            .values(id=1, organisation_id=1, name="s", fs=1500.0, description="", created_at=now)
        )
        connection.execute(
            table["model_versions"].insert().values(
                id=1, structure_id=1, kind="fault_mode", name="k2", version=1, document={}, training={},
                statistics={}, active=True, created_at=now,
            )
        )  # fmt: skip
        connection.execute(
            table["records"].insert().values(
                id=1, structure_id=1, fs=1500.0, n_samples=3, acquired_at=now, created_at=now,
                sha256="0" * 64, x=b"", y=b"",
            )
        )  # fmt: skip
        connection.execute(
            table["verdicts"].insert().values(
                id=1, record_id=1, structure_id=1, acquired_at=now, created_at=now, model_set="1",
                status="healthy", fault_detected=False, alpha=0.05, lags=4, n_samples=3, z_critical=1.96,
                q_critical_detection=1.0, detected_by=[], modes=[],
            )
        )  # fmt: skip
        connection.execute(table["verdict_models"].insert().values(verdict_id=1, model_version_id=1))
        connection.execute(
            STATES_BEFORE_0024.insert().values(
                structure_id=1, organisation_id=1, status="healthy", since=now, latest_verdict_id=1,
                latest_acquired_at=now, records=1, healthy=1, faulty=0, unknown_fault=0,
            )
        )  # fmt: skip
    upgrade_database(fresh_url)
    with engine.connect() as connection:
        assert connection.execute(text("SELECT verdict_id, model_version_id FROM verdict_models")).all() == [
            (1, 1)
        ]
        assert connection.execute(text("SELECT latest_verdict_id FROM structure_states")).scalar_one() == 1
    engine.dispose()


def test_0020_is_undone_only_once_no_refinement_without_a_base_model_is_stored(fresh_url):
    """A refinement from the linear orders the loop chose has no base model, which the schema
    before 0020 cannot hold: downgrading is refused, naming how many, while one is stored (and
    nothing changes); once it is deleted it goes through and keeps the refinement from a base."""
    upgrade_database(fresh_url)
    _structure_with_records(fresh_url, None)
    engine = make_engine(fresh_url)
    now = utcnow()
    with engine.begin() as connection:
        connection.execute(
            tables.ModelVersion.__table__.insert().values(
                id=1, structure_id=1, kind="baseline", name="baseline", version=1, document={}, training={},
                statistics={}, active=True, created_at=now,
            )
        )  # fmt: skip
        record_id = connection.execute(text("SELECT id FROM records")).scalar_one()
        for refinement_id, base in ((1, 1), (2, None)):
            connection.execute(
                tables.Refinement.__table__.insert().values(
                    id=refinement_id, structure_id=1, record_id=record_id, base_model_id=base, report={},
                    created_at=now,
                )
            )  # fmt: skip
    engine.dispose()
    refused = r"^1 refinement\(s\) without a base model are stored"
    downgraded_once_deleted(fresh_url, "0019", refused, "DELETE FROM refinements WHERE base_model_id IS NULL")
    schema, _ = schema_and_revision(fresh_url)
    assert ("base_model_id", "INTEGER", False) in schema["refinements"]["columns"]
    engine = make_engine(fresh_url)
    with engine.connect() as connection:
        assert connection.execute(text("SELECT id, base_model_id FROM refinements")).all() == [(1, 1)]
    engine.dispose()


def test_0021_seals_the_webhooks_secrets_under_the_servers_keys_and_undoes_it(fresh_url, monkeypatch):
    """Secrets stored as given before 0021 are sealed by it (none left readable in the table, each
    opened by the server's key alone), and downgrading gives them back as they were."""
    key = Fernet.generate_key().decode()
    monkeypatch.setenv("NARXWATCH_SECRET_KEYS", json.dumps([key]))
    secrets = {1: "whsec_" + "a" * 40, 2: "s" * 200}  # the longest the API takes
    upgrade_database(fresh_url, "0020")
    engine = make_engine(fresh_url)
    now = dt.datetime.now(dt.UTC)
    with engine.begin() as connection:
        connection.execute(
            text("INSERT INTO organisations (id, name, created_at) VALUES (1, 'o', :t)"), {"t": now}
        )
        for webhook_id, secret in secrets.items():
            connection.execute(
                text("INSERT INTO webhooks (id, organisation_id, url, secret, events, created_at) "
                     "VALUES (:i, 1, 'https://93.184.215.14/hook', :s, '[\"alarm.opened\"]', :t)"),
                {"i": webhook_id, "s": secret, "t": now},
            )  # fmt: skip

    def stored() -> dict[int, str]:
        with engine.connect() as connection:
            return {i: secret for i, secret in connection.execute(text("SELECT id, secret FROM webhooks"))}

    upgrade_database(fresh_url)
    sealed = stored()
    assert all(secrets[i] not in sealed[i] for i in secrets)
    assert {i: Fernet(key).decrypt(token.encode()).decode() for i, token in sealed.items()} == secrets
    command.downgrade(alembic_config(fresh_url), "0020")
    assert stored() == secrets
    engine.dispose()


def test_0022_reads_each_state_again_without_the_verdicts_acquired_in_the_future(fresh_url):
    """A structure whose state took a verdict dated 9999 for its latest (before acquisition times
    were checked) stands after 0022 on the newest verdict acquired up to the server's clock plus
    the skew allowed, its run read from those alone; one with only a future verdict is
    uninspected. The counts, and the states of structures without such a verdict, stay."""
    upgrade_database(fresh_url, "0021")
    engine = make_engine(fresh_url)
    now = utcnow()
    day = dt.timedelta(days=1)
    t0 = dt.datetime(2026, 6, 1, tzinfo=dt.UTC)
    future = dt.datetime(9999, 12, 31, tzinfo=dt.UTC)
    soon = now + dt.timedelta(seconds=60)  # within the default skew: the present
    table = Base.metadata.tables
    # (verdict id, structure, acquired, status), and each structure's state as the code before left it.
    history = [
        (1, 1, t0 + day, "healthy"), (2, 1, t0 + 2 * day, "faulty"), (3, 1, t0 + 3 * day, "faulty"),
        (4, 1, soon, "faulty"), (5, 1, future, "healthy"), (6, 2, future, "faulty"), (7, 3, t0, "healthy"),
    ]  # fmt: skip
    states = {
        1: dict(status="healthy", since=future, latest_verdict_id=5, latest_acquired_at=future, healthy=2,
                faulty=3),
        2: dict(status="faulty", since=future, latest_verdict_id=6, latest_acquired_at=future, faulty=1),
        3: dict(status="healthy", since=t0 - day, latest_verdict_id=7, latest_acquired_at=t0, healthy=1),
    }  # fmt: skip
    with engine.begin() as connection:
        connection.execute(table["organisations"].insert().values(id=1, name="o", created_at=now))
        for structure_id in states:
            connection.execute(
                table["structures"].insert().values(
                    id=structure_id, organisation_id=1, name=f"s{structure_id}", fs=1500.0, description="",
                    created_at=now,
                )
            )  # fmt: skip
        for verdict_id, structure_id, acquired, status in history:
            connection.execute(
                table["records"].insert().values(
                    id=verdict_id, structure_id=structure_id, fs=1500.0, n_samples=3, acquired_at=acquired,
                    created_at=now, sha256=f"{verdict_id:064d}", x=b"", y=b"",
                )
            )  # fmt: skip
            connection.execute(
                table["verdicts"].insert().values(
                    id=verdict_id, record_id=verdict_id, structure_id=structure_id, acquired_at=acquired,
                    created_at=now, model_set="1", status=status, fault_detected=status != "healthy",
                    alpha=0.05, lags=4, n_samples=3, z_critical=1.96, q_critical_detection=1.0,
                    detected_by=[], modes=[],
                )
            )  # fmt: skip
        for structure_id, state in states.items():
            records = sum(1 for _, s, _, _ in history if s == structure_id)
            connection.execute(
                STATES_BEFORE_0024.insert().values(
                    structure_id=structure_id, organisation_id=1, records=records,
                    **{"healthy": 0, "faulty": 0, "unknown_fault": 0} | state,
                )
            )  # fmt: skip
    upgrade_database(fresh_url)
    with Session(engine) as session:
        after = {s.structure_id: s for s in session.scalars(select(tables.StructureState))}
    engine.dispose()
    standing = {
        structure_id: (s.status, s.since, s.latest_verdict_id, s.latest_acquired_at)
        for structure_id, s in after.items()
    }
    assert standing == {
        1: ("faulty", t0 + 2 * day, 4, soon),
        2: (None, None, None, None),
        3: ("healthy", t0 - day, 7, t0),  # no future verdict: left as it was, however it was read
    }
    tallies = {structure_id: (s.records, s.healthy, s.faulty) for structure_id, s in after.items()}
    assert tallies == {1: (5, 2, 3), 2: (1, 0, 1), 3: (1, 1, 0)}


def test_0023_keeps_no_rule_state_until_the_rules_run_then_builds_it_from_the_history(fresh_url):
    """A structure judged before 0023 has no kept rule state: its next verdict's evaluation builds
    it from the history, so the rules count the verdicts stored before the upgrade (here the two
    faulty ones that, with a third, make persistence's 3 of 5), and the next goes on from it.
    Downgrading drops the table."""
    from service.domain import alarms

    upgrade_database(fresh_url, "0022")
    engine = make_engine(fresh_url)
    now = dt.datetime.now(dt.UTC)
    t0 = dt.datetime(2026, 6, 1, tzinfo=dt.UTC)
    table = Base.metadata.tables
    with engine.begin() as connection:
        _organisation_and_structure(connection, now)
        for n in (1, 2, 3):
            connection.execute(
                table["records"].insert().values(
                    id=n, structure_id=1, fs=1500.0, n_samples=3, acquired_at=t0 + n * dt.timedelta(hours=1),
                    created_at=now, sha256=f"{n:064d}", x=b"", y=b"",
                )
            )  # fmt: skip
        for n, status in ((1, "faulty"), (2, "faulty")):
            connection.execute(
                table["verdicts"].insert().values(
                    id=n, record_id=n, structure_id=1, acquired_at=t0 + n * dt.timedelta(hours=1),
                    created_at=now, model_set="1", status=status, fault_detected=True, alpha=0.05, lags=4,
                    n_samples=3, z_critical=1.96, q_critical_detection=1.0, detected_by=[], modes=[],
                )
            )  # fmt: skip
    upgrade_database(fresh_url)
    with Session(engine) as session:
        assert session.scalars(select(tables.AlarmState)).all() == []
        at = t0 + 3 * dt.timedelta(hours=1)
        session.execute(
            table["verdicts"].insert().values(
                id=3, record_id=3, structure_id=1, acquired_at=at, created_at=now, model_set="1",
                status="faulty", fault_detected=True, alpha=0.05, lags=4, n_samples=3, z_critical=1.96,
                q_critical_detection=1.0, detected_by=[], modes=[],
            )
        )  # fmt: skip
        structure = session.get(tables.Structure, 1)
        limit = at + dt.timedelta(days=1)
        alarms.evaluate(session, structure, limit, alarms.point(3, 3, at, "faulty", None, None, None, []))
        session.commit()
        kept = alarms.Kept.loads(session.scalar(select(tables.AlarmState.state)))
        rebuilt = alarms._replay(session, 1, list(alarms.DEFAULT_RULES), limit)
        opened = session.execute(select(tables.Alarm.rule_kind, tables.Alarm.record_id)).all()
    assert kept.tracks["persistence"].flags == [True, True, True] and kept == rebuilt
    assert kept.newest == [3, 3, alarms._microseconds(at)]
    assert opened == [("persistence", 3)]  # one faulty verdict alone fires no rule

    command.downgrade(alembic_config(fresh_url), "0022")
    with engine.connect() as connection:
        left = set(inspect(connection).get_table_names())
    engine.dispose()
    assert "alarm_states" not in left and "verdicts" in left


def test_0024_counts_no_anomaly_before_and_is_undone_only_once_no_baseline_verdict_is_stored(fresh_url):
    """A structure's state from before 0024 counts no anomaly; a verdict of a healthy baseline
    alone (no Ljung–Box lags, its figures in ``novelty``) can then be stored. The schema before
    cannot hold one: downgrading is refused, naming how many, while one is stored; once it is
    deleted it goes through and keeps the chain's verdict."""
    upgrade_database(fresh_url, "0023")
    _structure_with_records(fresh_url, None, None)
    engine = make_engine(fresh_url)
    now = utcnow()
    table = Base.metadata.tables
    chain = dict(
        structure_id=1, acquired_at=now, created_at=now, model_set="1", alpha=0.05, n_samples=2,
        z_critical=None, q_critical_detection=None, detected_by=[], modes=[],
    )  # fmt: skip
    with engine.begin() as connection:
        connection.execute(
            STATES_BEFORE_0024.insert().values(
                structure_id=1, organisation_id=1, records=2, healthy=1, faulty=0, unknown_fault=0
            )
        )
        first, second = connection.execute(text("SELECT id FROM records ORDER BY id")).scalars().all()
        connection.execute(
            text(
                "INSERT INTO verdicts (id, record_id, structure_id, acquired_at, created_at, model_set, "
                "status, fault_detected, alpha, lags, n_samples, detected_by, modes) "
                "VALUES (1, :record, 1, :t, :t, '1', 'healthy', false, 0.05, 40, 2, '[]', '[]')"
            ),
            {"record": first, "t": now},
        )
    upgrade_database(fresh_url)
    with engine.begin() as connection:
        assert connection.execute(text("SELECT anomaly FROM structure_states")).scalar_one() == 0
        connection.execute(
            table["verdicts"].insert().values(
                id=2, record_id=second, status="anomaly", fault_detected=True, lags=None,
                novelty={"statistic": 9.0, "threshold": 1.6, "severity": 1.3}, **chain,
            )
        )  # fmt: skip
    engine.dispose()
    downgraded_once_deleted(
        fresh_url,
        "0023",
        r"^1 verdict\(s\) of a healthy baseline alone are stored",
        "DELETE FROM verdicts WHERE lags IS NULL",
    )
    nullable = {
        name: {column: null for column, _, null in kept["columns"]}
        for name, kept in schema_and_revision(fresh_url)[0].items()
    }
    assert nullable["verdicts"]["lags"] is False and "novelty" not in nullable["verdicts"]
    assert "anomaly" not in nullable["structure_states"]
    engine = make_engine(fresh_url)
    with engine.connect() as connection:
        assert connection.execute(text("SELECT id, status, lags FROM verdicts")).all() == [(1, "healthy", 40)]
    engine.dispose()


def test_0025_leaves_the_structures_stored_before_it_undeclared_and_undoes_cleanly(fresh_url):
    """Structures stored before 0025 keep their rows, with no quantity or unit declared (read as
    none: plain x and y), and what refers to them stays; downgrading drops the declarations and
    keeps the structures."""
    upgrade_database(fresh_url, "0023")
    engine = make_engine(fresh_url)
    now = dt.datetime.now(dt.UTC)
    with engine.begin() as connection:
        _organisation_and_structure(connection, now)
        connection.execute(
            text("INSERT INTO structure_states (structure_id, organisation_id, records, healthy, faulty, "
                 "unknown_fault) VALUES (1, 1, 0, 0, 0, 0)")
        )  # fmt: skip
    upgrade_database(fresh_url)
    with Session(engine) as session:
        structure = session.get(tables.Structure, 1)
        assert (structure.name, structure.fs) == ("s", 1500.0)
        assert structure.excitation is None and structure.response is None
        structure.response_quantity, structure.response_unit = "acceleration", "m/s²"
        session.commit()
    command.downgrade(alembic_config(fresh_url), "0024")
    with engine.connect() as connection:
        columns = {c["name"] for c in inspect(connection).get_columns("structures")}
        kept = connection.execute(text("SELECT id, name, fs FROM structures")).all()
        states = connection.execute(text("SELECT structure_id FROM structure_states")).scalars().all()
    engine.dispose()
    assert not columns & {"excitation_quantity", "excitation_unit", "response_quantity", "response_unit"}
    assert kept == [(1, "s", 1500.0)] and states == [1]
