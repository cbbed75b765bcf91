"""The Alembic migrations build exactly the schema the code declares, on both databases."""

from __future__ import annotations

import uuid

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import inspect

from service import tables  # noqa: F401  (registers the tables)
from service.db import Base, make_engine
from service.migrate import is_ours, upgrade_database


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


def test_upgrade_is_idempotent(fresh_url):
    upgrade_database(fresh_url)
    upgrade_database(fresh_url)
