"""Schema upgrades through Alembic, from the command line or at service start."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from alembic import command
from alembic.config import Config
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import create_engine
from sqlalchemy.engine import make_url
from sqlalchemy.exc import OperationalError

from service.errors import UPGRADE_HINT, DatabaseNotReadyError, DatabaseUnreachableError


def is_ours(name: str | None, type_: str, _parents: object) -> bool:
    """Alembic's ``include_name`` filter: Procrastinate's tables are its own, not our metadata's."""
    return not (type_ == "table" and name is not None and name.startswith("procrastinate_"))


def alembic_config(database_url: str) -> Config:
    config = Config()
    config.set_main_option("script_location", str(resources.files("migrations")))
    config.set_main_option("sqlalchemy.url", database_url)
    return config


def upgrade_database(database_url: str, revision: str = "head") -> None:
    """Bring the schema at ``database_url`` to ``revision`` (default: the newest)."""
    command.upgrade(alembic_config(database_url), revision)


def database_name(database_url: str) -> str:
    """How a person recognises the database: a SQLite file's absolute path, else the URL without
    its password."""
    url = make_url(database_url)
    if url.get_backend_name() == "sqlite" and url.database and url.database != ":memory:":
        return str(Path(url.database).resolve())
    return url.render_as_string(hide_password=True)


def require_current_schema(database_url: str) -> None:
    """Refuse a database that is missing or not at the newest revision, creating nothing.

    Every command but ``db upgrade``, ``demo-seed`` and ``serve`` (which upgrade) checks this
    first: opening a SQLite URL creates an empty file, and an empty schema would fail later as a
    long traceback about a missing table.
    """
    where = database_name(database_url)
    url = make_url(database_url)
    if url.get_backend_name() == "sqlite" and url.database != ":memory:" and not Path(where).is_file():
        raise DatabaseNotReadyError(f"no database at {where}: {UPGRADE_HINT} to create it")
    heads = set(ScriptDirectory.from_config(alembic_config(database_url)).get_heads())
    engine = create_engine(database_url)
    try:
        with engine.connect() as connection:
            current = set(MigrationContext.configure(connection).get_current_heads())
    except OperationalError as exc:
        reason = str(exc.orig).strip().splitlines()[0] if exc.orig else str(exc)
        raise DatabaseUnreachableError(f"cannot open the database at {where}: {reason}") from None
    finally:
        engine.dispose()
    if current != heads:
        at = ", ".join(sorted(current)) or "no revision (empty)"
        raise DatabaseNotReadyError(
            f"the database at {where} is at {at}, not {', '.join(sorted(heads))}: {UPGRADE_HINT}"
        )
