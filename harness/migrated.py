"""New databases already at a schema revision, for tests that need one of their own.

Migrating a new database runs every revision again: most of a second of a test's set-up on
SQLite, more on PostgreSQL. Each database here is instead a copy of one migrated once a process
(per PostgreSQL server) to the same revision: a SQLite file copied, a PostgreSQL database created
from it as its template (``CREATE DATABASE … TEMPLATE`` copies the template's files). What is
copied is what ``upgrade_database`` made; the tests that the revisions run from an empty database
start from one (``harness.postgres.create_database``, a new SQLite path).
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

HEAD = "head"
_templates: set[tuple[str, str]] = set()  # (server: its URL without the database, revision)


def _template_name(revision: str) -> str:
    """The template database of ``revision`` on each test PostgreSQL server; nothing connects to
    it once it is made."""
    return "narxwatch_migrated" if revision == HEAD else f"narxwatch_at_{revision}"


@functools.cache
def _sqlite_folder() -> Path:
    folder = Path(tempfile.mkdtemp(prefix="nxsqlite-"))
    atexit.register(shutil.rmtree, folder, True)
    return folder


@functools.cache
def _sqlite_template(revision: str) -> Path:
    path = _sqlite_folder() / f"{revision}.db"
    upgrade_database(f"sqlite:///{path}", revision)  # disposes its engine: the log is merged
    if path.with_name(path.name + "-wal").exists():
        raise RuntimeError(f"{path}'s write-ahead log outlived the migration: a copy would miss it")
    return path


def sqlite(path: Path, revision: str = HEAD) -> str:
    """A new SQLite file at ``path`` (its folder made if need be) at ``revision``; its URL."""
    path.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(_sqlite_template(revision), path)
    return f"sqlite:///{path}"


def postgresql(server_url: str, name: str, revision: str = HEAD) -> str:
    """A new database ``name`` at ``revision`` on the server of ``server_url``; its URL."""
    import psycopg
    from psycopg import sql

    if not re.fullmatch(r"[a-z_][a-z0-9_]*", name):
        raise ValueError(f"database name must be a lowercase identifier: {name!r}")
    server, template = server_url.rsplit("/", 1)[0], _template_name(revision)
    if (server, revision) not in _templates:
        upgrade_database(postgres.create_database(server_url, template), revision)
        _templates.add((server, revision))
    with psycopg.connect(postgres.conninfo(server_url), autocommit=True) as conn:
        conn.execute(
            sql.SQL("CREATE DATABASE {} TEMPLATE {}").format(sql.Identifier(name), sql.Identifier(template))
        )
    return f"{server}/{name}"
