"""Database engine and sessions: one session per request, committed or rolled back whole."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import make_url
from sqlalchemy.orm import DeclarativeBase, Session, sessionmaker


class Base(DeclarativeBase):
    pass


_INSERTS = {"sqlite": sqlite.insert, "postgresql": postgresql.insert}


def make_engine(url: str) -> Engine:
    """An engine for ``url``; a SQLite file gets its folder, WAL journaling and foreign keys."""
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite":
        return create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=20)
    if parsed.database and parsed.database != ":memory:":
        Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)
    engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30})

    @event.listens_for(engine, "connect")
    def _configure(connection, _record) -> None:  # type: ignore[no-untyped-def]
        cursor = connection.cursor()
        # WAL lets readers proceed during a write; NORMAL sync is durable across process
        # crashes (fsync at checkpoints), which is what a monitoring record store needs.
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute("PRAGMA synchronous=NORMAL")
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.close()

    return engine


def insert_unless_exists(
    session: Session, model: type[Base], values: dict[str, Any], unique: list[str]
) -> Any | None:
    """``INSERT … ON CONFLICT DO NOTHING``: the new row's ``id`` and ``created_at``, or None if
    the unique columns match an existing row.

    Concurrent duplicates (the same upload twice, a redelivered inspection) are settled by the
    database without savepoints. pysqlite turns a savepoint's release into a commit, and it
    starts a transaction only at the first write: that keeps SQLite's write lock short and lets
    writers wait for it instead of failing.
    """
    dialect = session.get_bind().dialect.name
    statement = _INSERTS[dialect](model).values(**values).on_conflict_do_nothing(index_elements=unique)
    returning = statement.returning(model.id, model.created_at)  # type: ignore[attr-defined]
    return session.execute(returning).one_or_none()


def session_factory(engine: Engine) -> sessionmaker[Session]:
    return sessionmaker(engine, expire_on_commit=False)


@contextmanager
def transaction(factory: sessionmaker[Session]) -> Iterator[Session]:
    """A session whose work is committed on success and rolled back whole on any error."""
    with factory() as session, session.begin():
        yield session
