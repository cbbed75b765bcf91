"""The Alembic migrations build exactly the schema the code declares, on both databases."""

from __future__ import annotations

import datetime as dt
import uuid

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import inspect, select, text
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service import tables
from service.db import Base, make_engine
from service.migrate import is_ours, upgrade_database
from service.tables import utcnow


@pytest.fixture(params=["sqlite", "postgresql"])
def fresh_url(request, tmp_path):
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'm.db'}"
    import postgres

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


def test_0006_keeps_the_newest_of_two_active_versions(fresh_url):
    """A database left with two active versions of one name (before 0006) keeps only the newest
    active, and from then on the database refuses a second active version."""
    upgrade_database(fresh_url, "0005")
    engine = make_engine(fresh_url)
    versions = Base.metadata.tables["model_versions"]
    now = dt.datetime.now(dt.UTC)
    with engine.begin() as connection:
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
