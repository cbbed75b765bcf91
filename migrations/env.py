"""Alembic environment, wired to narxwatch's settings (NARXWATCH_DATABASE_URL)."""

from __future__ import annotations

from alembic import context

from service import tables  # noqa: F401  (registers every table on the metadata)
from service.config import get_settings
from service.db import Base, make_engine
from service.migrate import is_ours

config = context.config
url = config.get_main_option("sqlalchemy.url") or get_settings().database_url


def run_migrations_offline() -> None:
    context.configure(
        url=url,
        target_metadata=Base.metadata,
        literal_binds=True,
        render_as_batch=True,
        include_name=is_ours,
    )
    with context.begin_transaction():
        context.run_migrations()


def run_migrations_online() -> None:
    engine = make_engine(url)
    with engine.connect() as connection:
        if connection.dialect.name == "sqlite":
            # Batch mode rebuilds a table to alter it: copy, drop, rename. With foreign keys
            # enforced (as every narxwatch connection has them), dropping the old table fires the
            # ON DELETE actions of every row referring to it — verdict_models' links deleted,
            # structure_states' latest verdicts set to NULL. The pragma is a no-op inside a
            # transaction, so it is committed alone before the migrations' transaction begins.
            connection.exec_driver_sql("PRAGMA foreign_keys=OFF")
            connection.commit()
        # Batch mode lets ALTER TABLE work on SQLite, which rebuilds tables to change them.
        # One transaction for the whole run, on SQLite as on PostgreSQL: Alembic would otherwise
        # commit each revision on SQLite, and pysqlite each CREATE, DROP or ALTER alone (it begins
        # a transaction only before a write of rows), so that a revision refused halfway (0015's
        # downgrade with records of several channels stored) left those before it undone.
        context.configure(
            connection=connection,
            target_metadata=Base.metadata,
            render_as_batch=True,
            include_name=is_ours,
            transactional_ddl=True,
        )
        with context.begin_transaction():
            if connection.dialect.name == "sqlite":
                connection.exec_driver_sql("BEGIN")
            context.run_migrations()
            if connection.dialect.name == "sqlite":
                broken = connection.exec_driver_sql("PRAGMA foreign_key_check").fetchall()
                if broken:
                    raise RuntimeError(f"the migration left rows whose references are broken: {broken[:5]}")
    engine.dispose()


if context.is_offline_mode():
    run_migrations_offline()
else:
    run_migrations_online()
