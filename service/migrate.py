"""Schema upgrades through Alembic, from the command line or at service start."""

from __future__ import annotations

from importlib import resources

from alembic import command
from alembic.config import Config


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
