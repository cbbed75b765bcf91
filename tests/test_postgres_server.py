"""The throwaway PostgreSQL server of harness/postgres.py works: connect, write, read, roll back."""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import psycopg
import pytest
from sqlalchemy import Engine, create_engine, text
from sqlalchemy.engine import make_url

from harness import migrated, postgres


@pytest.fixture(scope="module")
def engine(postgres_url: str):  # yields Engine
    postgres.reset_database(postgres_url)
    engine = create_engine(postgres_url)
    yield engine
    engine.dispose()
    postgres.reset_database(postgres_url)


def test_url_is_a_local_psycopg_url(postgres_url: str) -> None:
    url = make_url(postgres_url)
    assert url.drivername == "postgresql+psycopg"
    assert url.host == "127.0.0.1"
    assert url.port is not None and url.port > 0
    assert url.username == postgres.USER
    assert url.database == postgres.DATABASE


def test_server_answers(engine: Engine) -> None:
    with engine.connect() as conn:
        version = conn.execute(text("select version()")).scalar_one()
        assert version.startswith("PostgreSQL ")
        assert conn.execute(text("select current_database()")).scalar_one() == postgres.DATABASE
        assert conn.execute(text("show server_encoding")).scalar_one() == "UTF8"
        assert conn.execute(text("show fsync")).scalar_one() == "off"


def test_write_and_read_back(engine: Engine) -> None:
    with engine.begin() as conn:
        conn.execute(text("create table reading (id serial primary key, sensor text not null, value float8)"))
        conn.execute(
            text("insert into reading (sensor, value) values (:sensor, :value)"),
            [{"sensor": "y", "value": 1.5}, {"sensor": "ü-σ", "value": -2.25}],
        )
    with engine.connect() as conn:
        rows = conn.execute(text("select sensor, value from reading order by id")).all()
    assert [tuple(row) for row in rows] == [("y", 1.5), ("ü-σ", -2.25)]


def test_rollback_leaves_nothing_written(engine: Engine) -> None:
    with engine.begin() as conn:
        conn.execute(text("create table event (id integer primary key, note text)"))

    class AbortError(Exception):
        pass

    with pytest.raises(AbortError), engine.begin() as conn:
        conn.execute(text("insert into event values (1, 'lost')"))
        assert conn.execute(text("select count(*) from event")).scalar_one() == 1
        raise AbortError

    with engine.connect() as conn:
        assert conn.execute(text("select count(*) from event")).scalar_one() == 0
        conn.execute(text("insert into event values (2, 'rolled back explicitly')"))
        conn.rollback()
        assert conn.execute(text("select count(*) from event")).scalar_one() == 0


def test_reset_database_drops_everything(postgres_url: str, engine: Engine) -> None:
    with engine.begin() as conn:
        conn.execute(text("create table leftover (id integer)"))
    postgres.reset_database(postgres_url)
    with engine.connect() as conn:
        tables = conn.execute(text("select tablename from pg_tables where schemaname = 'public'")).all()
    assert tables == []


def test_the_session_server_keeps_its_files_in_memory_where_the_machine_has_a_tmpfs(engine: Engine) -> None:
    """Nothing of it is kept: its files, the tests' template copies among them, are written to
    a tmpfs and deleted from it, never to a disk."""
    with engine.connect() as conn:
        data = Path(conn.execute(text("show data_directory")).scalar_one())
    assert data.is_relative_to(postgres.MEMORY) == postgres.in_memory_room(), data


def test_a_copy_of_the_migrated_template_is_not_written_to_the_wal(postgres_url: str) -> None:
    """``harness.migrated`` copies the template's files: the write-ahead log grows by a few
    records, not by the copy's blocks (PostgreSQL's default since 15, slower for many copies)."""
    migrated.postgresql(postgres_url, f"wal_{uuid.uuid4().hex[:12]}")  # the template made first
    with psycopg.connect(postgres.conninfo(postgres_url), autocommit=True) as conn:
        before = conn.execute("SELECT pg_current_wal_lsn()").fetchone()[0]
        copy = migrated.postgresql(postgres_url, f"wal_{uuid.uuid4().hex[:12]}")
        written, size = conn.execute(
            "SELECT pg_wal_lsn_diff(pg_current_wal_lsn(), %s), pg_database_size(%s)",
            (before, copy.rsplit("/", 1)[1]),
        ).fetchone()
    assert written < size / 10, f"{written} bytes of WAL for a copy of {size} bytes"


SERVE_UNTIL_KILLED = """
import sys, time
from harness import postgres
with postgres.postgres_instance() as server:
    print(server.data.parent, server.port, flush=True)
    time.sleep(600)
"""


def test_a_server_whose_test_process_is_killed_is_stopped_and_its_files_removed(postgres_url: str) -> None:
    """pg_ctl detaches the server: without the watchdog a killed test run left it running, with
    its port, memory and tmpfs files, until the machine restarted."""
    process = subprocess.Popen(
        [sys.executable, "-c", SERVE_UNTIL_KILLED],
        cwd=Path(__file__).parents[1],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        workdir, port = process.stdout.readline().split()
    finally:
        process.kill()
        process.wait()
    deadline = time.monotonic() + 60
    while (Path(workdir).exists() or _accepts(int(port))) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _accepts(int(port)), "the server outlived its test process"
    assert not Path(workdir).exists(), "the server's files outlived its test process"


def _accepts(port: int) -> bool:
    with socket.socket() as probe:
        return probe.connect_ex((postgres.HOST, port)) == 0


def test_a_server_stopped_while_clients_connect_stops() -> None:
    """A fast shutdown waits for each connection accepted while it runs until the client sends
    its startup packet or the server's authentication timeout passes: a client that connected
    then and never spoke (a narxwatch worker's connection attempt abandoned as it lost the
    database) kept a server stopped under load running past pg_ctl's wait, and the test went on
    as if it were down. Here clients keep connecting, and never speak, while it stops."""
    with postgres.postgres_instance("stopping", durable=True) as server:
        if server is None:
            pytest.skip(f"PostgreSQL unavailable: {postgres.missing_reason()}")
        held: list[socket.socket] = []
        stopped = threading.Event()

        def connect_and_say_nothing() -> None:
            while not stopped.is_set():
                with contextlib.suppress(OSError):
                    held.append(socket.create_connection((postgres.HOST, server.port), timeout=1))
                time.sleep(0.05)

        connecting = threading.Thread(target=connect_and_say_nothing)
        connecting.start()
        try:
            server.stop("fast")
        finally:
            stopped.set()
            connecting.join()
            for client in held:
                client.close()
        assert not (server.data / "postmaster.pid").exists() and not _accepts(server.port)
