"""New databases already at the newest schema revision, for tests that need one of their own.

Migrating a new database runs every revision again: most of a second of a test's set-up on
SQLite, more on PostgreSQL. Each database here is instead a copy of one migrated once a process
(per PostgreSQL server): a SQLite file copied, a PostgreSQL database created from it as its
template (``CREATE DATABASE … TEMPLATE`` copies the template's files). What is copied is what
``upgrade_database`` made; the tests of the migrations themselves start from empty databases
(``harness.postgres.create_database``, a new SQLite path).
"""

from __future__ import annotations

import atexit
import functools
import re
import shutil
import tempfile
from pathlib import Path

from harness import postgres
from service.migrate import upgrade_database

TEMPLATE = "narxwatch_migrated"  # on each test PostgreSQL server; nothing connects to it after
_templates: set[str] = set()  # the servers (their URLs without a database) that have one
FILE_COPY_SINCE = 150000  # server_version_num of PostgreSQL 15, which added CREATE DATABASE's STRATEGY


@functools.cache
def _sqlite_template() -> Path:
    folder = Path(tempfile.mkdtemp(prefix="nxsqlite-"))
    atexit.register(shutil.rmtree, folder, True)
    path = folder / "migrated.db"
    upgrade_database(f"sqlite:///{path}")  # disposes its engine: the write-ahead log is merged
    if path.with_name(path.name + "-wal").exists():
        raise RuntimeError(f"{path}'s write-ahead log outlived the migration: a copy would miss it")
    return path


def sqlite(path: Path) -> str:
    """A new SQLite file at ``path`` (its folder made if need be) at the newest revision; its URL."""
    path.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(_sqlite_template(), path)
    return f"sqlite:///{path}"


def postgresql(server_url: str, name: str) -> str:
    """A new database ``name`` at the newest revision on the server of ``server_url``; its URL."""
    import psycopg
    from psycopg import sql

    if not re.fullmatch(r"[a-z_][a-z0-9_]*", name):
        raise ValueError(f"database name must be a lowercase identifier: {name!r}")
    server = server_url.rsplit("/", 1)[0]
    if server not in _templates:
        upgrade_database(postgres.create_database(server_url, TEMPLATE))
        _templates.add(server)
    with psycopg.connect(postgres.conninfo(server_url), autocommit=True) as conn:
        # The template's files copied as files: by default PostgreSQL 15 on writes every block of
        # the copy to its write-ahead log instead, which for a template this small is slower and
        # fills the log with copies (before 15, files were the only way).
        strategy = " STRATEGY FILE_COPY" if conn.info.server_version >= FILE_COPY_SINCE else ""
        create = sql.SQL("CREATE DATABASE {} TEMPLATE {}" + strategy)
        conn.execute(create.format(sql.Identifier(name), sql.Identifier(TEMPLATE)))
    return f"{server}/{name}"
