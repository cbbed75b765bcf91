"""Database engine and sessions: one session per request, committed or rolled back whole."""

from __future__ import annotations

import contextlib
import fcntl
import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import IO, Any

from sqlalchemy import Engine, Executable, create_engine, event
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import URL, make_url
from sqlalchemy.orm import DeclarativeBase, Session, sessionmaker


class Base(DeclarativeBase):
    pass


_INSERTS = {"sqlite": sqlite.insert, "postgresql": postgresql.insert}


def make_engine(url: str, pool_timeout: float = 30.0) -> Engine:
    """An engine for ``url``; a SQLite file gets its folder, WAL journaling, foreign keys and the
    writer gate. A request for a connection waits at most ``pool_timeout`` seconds for the pool
    (then ``sqlalchemy.exc.TimeoutError``); the service passes NARXWATCH_POOL_TIMEOUT_SECONDS."""
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite":
        return create_engine(
            url, pool_pre_ping=True, pool_size=10, max_overflow=20, pool_timeout=pool_timeout
        )
    connect_args = {"check_same_thread": False, "timeout": 30, "factory": GatedConnection}
    gate = writer_gate(parsed)
    if gate is None:  # in memory: one connection, no pool to wait for
        engine = create_engine(url, connect_args=connect_args)
    else:
        Path(parsed.database).parent.mkdir(parents=True, exist_ok=True)  # type: ignore[arg-type]
        engine = create_engine(url, connect_args=connect_args, pool_timeout=pool_timeout)

    @event.listens_for(engine, "connect")
    def _configure(connection, _record) -> None:  # type: ignore[no-untyped-def]
        connection.gate = gate
        cursor = connection.cursor()
        # WAL lets readers proceed during a write; NORMAL sync is durable across process
        # crashes (fsync at checkpoints), which is what a monitoring record store needs.
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute("PRAGMA synchronous=NORMAL")
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.close()

    return engine


def insert_unless_exists(
    session: Session,
    model: type[Base],
    values: dict[str, Any],
    unique: list[str],
    returning: tuple[str, ...] = ("id", "created_at"),
) -> Any | None:
    """``INSERT … ON CONFLICT DO NOTHING``: the new row's ``returning`` columns, or None if the
    unique columns match an existing row.

    Concurrent duplicates (the same upload twice, a redelivered inspection) are settled by the
    database without savepoints. pysqlite turns a savepoint's release into a commit, and it
    starts a transaction only at the first write: that keeps SQLite's write lock short and lets
    writers wait for it instead of failing.
    """
    statement = _insert_unless_exists(session.get_bind().dialect.name, model, tuple(unique), returning)
    return session.execute(statement, values).one_or_none()


@lru_cache(maxsize=64)
def _insert_unless_exists(
    dialect: str, model: type[Base], unique: tuple[str, ...], returning: tuple[str, ...]
) -> Executable:
    """Built once a kind: every upload inserts its record and its verdict."""
    table = model.__table__
    statement = _INSERTS[dialect](table).on_conflict_do_nothing(index_elements=list(unique))
    return statement.returning(*(table.c[name] for name in returning))


class WriterGate:
    """One writer at a time on a SQLite file, across the threads and processes that share it.

    SQLite admits one writer; the others retry on its busy handler, which sleeps 1, 2, 5, 10 …
    ms between tries, so under load a writer often sleeps past the moment the lock came free.
    Writers that queue here instead (a thread lock, then an advisory ``flock`` on a file next
    to the database) are woken as soon as the previous one committed. The engine takes it for
    every write transaction (``GatedConnection``); SQLite's own lock still guarantees correctness.
    """

    def __init__(self, database: Path) -> None:
        self._threads = threading.Lock()
        self._path = database.with_name(database.name + ".writer")
        self._handle: IO[str] | None = None

    def acquire(self) -> None:
        self._threads.acquire()
        try:
            handle = self._path.open("a")
            fcntl.flock(handle, fcntl.LOCK_EX)
        except BaseException:
            self._threads.release()
            raise
        self._handle = handle

    def release(self) -> None:
        """Let the next writer in; any thread may release what another acquired."""
        handle, self._handle = self._handle, None
        assert handle is not None, "the writer gate was released without being held"
        handle.close()  # releases the flock
        self._threads.release()

    @contextmanager
    def held(self) -> Iterator[None]:
        self.acquire()
        try:
            yield
        finally:
            self.release()


_GATES: dict[str, WriterGate] = {}


def writer_gate(url: str | URL) -> WriterGate | None:
    """The gate of a SQLite file (one per file in a process), or None where the database has no
    single-writer lock."""
    parsed = make_url(url)
    if parsed.get_backend_name() != "sqlite" or not parsed.database or parsed.database == ":memory:":
        return None
    path = Path(parsed.database).resolve()
    return _GATES.setdefault(str(path), WriterGate(path))


# pysqlite opens a transaction right before the first of these statements (and no other); it is
# SQLite's write transaction, so that is when the gate is taken.
_WRITES = ("INSERT", "UPDATE", "DELETE", "REPLACE")


class GatedConnection(sqlite3.Connection):
    """A pysqlite connection that holds its file's writer gate for each of its write transactions.

    The gate is taken before the statement that begins a write transaction and given back once
    that transaction has ended (commit, rollback, or the connection closed), whichever code
    wrote: requests, jobs, the command line and migrations alike. Reads never wait for it.
    """

    gate: WriterGate | None = None
    _holds_gate = False

    def cursor(self, factory: type[sqlite3.Cursor] | None = None) -> sqlite3.Cursor:  # type: ignore[override]
        return super().cursor(factory or _GatedCursor)

    def take_gate(self) -> None:
        if self.gate is not None and not self._holds_gate:
            self.gate.acquire()
            self._holds_gate = True

    def commit(self) -> None:
        try:
            super().commit()
        finally:  # a failed COMMIT leaves SQLite's own lock in charge until the rollback
            self._give_gate_back()

    def rollback(self) -> None:
        try:
            super().rollback()
        finally:
            self._give_gate_back()

    def close(self) -> None:
        try:
            super().close()
        finally:
            self._give_gate_back()

    def _give_gate_back(self) -> None:
        if self._holds_gate:
            self._holds_gate = False
            assert self.gate is not None
            self.gate.release()


class _GatedCursor(sqlite3.Cursor):
    connection: GatedConnection

    def execute(self, sql: str, parameters: Any = (), /) -> sqlite3.Cursor:  # type: ignore[override]
        if sql.lstrip()[:7].upper().startswith(_WRITES):
            self.connection.take_gate()
        return super().execute(sql, parameters)

    def executemany(self, sql: str, parameters: Any, /) -> sqlite3.Cursor:  # type: ignore[override]
        if sql.lstrip()[:7].upper().startswith(_WRITES):
            self.connection.take_gate()
        return super().executemany(sql, parameters)


def hold_writer_gate(session: Session) -> None:
    """Take the SQLite file's writer gate now, not at the transaction's first write: what the
    transaction computes from here on (an upload's acquisition time, say) then follows the order
    in which its writers commit. Nothing on other databases, where a row lock orders the writers
    of one structure."""
    connection = session.connection().connection.dbapi_connection
    if isinstance(connection, GatedConnection):
        connection.take_gate()


# The tables whose rows the retention empties or deletes, and the state rows it updates.
PRUNED_TABLES = (
    "records",
    "verdicts",
    "verdict_models",
    "record_conditions",
    "structure_states",
    "deliveries",
)


def vacuum(engine: Engine) -> None:
    """Give back the space of pruned rows. SQLite: ``VACUUM`` rewrites the file without it, which
    is the only way the file shrinks; it holds the writer gate throughout, so uploads wait for
    it (a minute or so a gigabyte). PostgreSQL reuses the space of dead rows once vacuumed, which
    autovacuum does by itself; ``VACUUM (ANALYZE)`` of the pruned tables does it now and
    refreshes the planner's statistics, locking out no reader or writer."""
    if engine.dialect.name == "sqlite":
        gate = writer_gate(engine.url)
        with contextlib.ExitStack() as stack, engine.connect() as connection:
            if gate is not None:
                stack.enter_context(gate.held())
            connection.exec_driver_sql("VACUUM")
            # In WAL mode the rewritten file sits in the log until a checkpoint copies it back.
            connection.exec_driver_sql("PRAGMA wal_checkpoint(TRUNCATE)")
        return
    with engine.connect().execution_options(isolation_level="AUTOCOMMIT") as connection:
        connection.exec_driver_sql(f"VACUUM (ANALYZE) {', '.join(PRUNED_TABLES)}")


def session_factory(engine: Engine) -> sessionmaker[Session]:
    return sessionmaker(engine, expire_on_commit=False)


@contextmanager
def transaction(factory: sessionmaker[Session]) -> Iterator[Session]:
    """A session whose work is committed on success and rolled back whole on any error."""
    with factory() as session, session.begin():
        yield session
