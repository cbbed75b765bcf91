"""Database engine and sessions: one session per request, committed or rolled back whole."""

from __future__ import annotations

import fcntl
import threading
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext
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
    table = model.__table__
    dialect = session.get_bind().dialect.name
    statement = _INSERTS[dialect](table).on_conflict_do_nothing(index_elements=unique)
    returning = statement.returning(table.c.id, table.c.created_at)
    return session.execute(returning, values).one_or_none()


class WriterGate:
    """One writer at a time on a SQLite file, across the threads and processes that share it.

    SQLite admits one writer; the others retry on its busy handler, which sleeps 1, 2, 5, 10 …
    ms between tries, so under load a writer often sleeps past the moment the lock came free.
    Writers that queue here instead (a thread lock, then an advisory ``flock`` on a file next
    to the database) are woken as soon as the previous one committed.
    """

    def __init__(self, database: Path) -> None:
        self._threads = threading.Lock()
        self._path = database.with_name(database.name + ".writer")

    @contextmanager
    def held(self) -> Iterator[None]:
        with self._threads, self._path.open("a") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)  # released when the file closes
            yield


_GATES: dict[str, WriterGate] = {}


def writer_gate(session: Session) -> WriterGate | None:
    """The gate of the session's SQLite file, or None where the database has no single-writer lock."""
    url = session.get_bind().url
    if url.get_backend_name() != "sqlite" or not url.database or url.database == ":memory:":
        return None
    return _GATES.setdefault(url.database, WriterGate(Path(url.database).resolve()))


@contextmanager
def writing(session: Session) -> Iterator[None]:
    """Hold the writer gate, if the database has one, around a session's writes and their commit."""
    gate = writer_gate(session)
    with gate.held() if gate is not None else nullcontext():
        yield


def session_factory(engine: Engine) -> sessionmaker[Session]:
    return sessionmaker(engine, expire_on_commit=False)


@contextmanager
def transaction(factory: sessionmaker[Session]) -> Iterator[Session]:
    """A session whose work is committed on success and rolled back whole on any error."""
    with factory() as session, session.begin():
        yield session
