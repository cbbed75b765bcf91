"""Errors the service's commands end with a one-line message for.

Kept apart from :mod:`service.migrate`, which raises them: the command line catches them for
every command, and importing the migrations' stack (Alembic, SQLAlchemy: about 0.6 s) to do so
would slow the commands that never open a database (``simulate``, ``train``, ``refine``, …).
"""

from __future__ import annotations

UPGRADE_HINT = "run `narxwatch db upgrade`"


class DatabaseNotReadyError(Exception):
    """The database is missing or behind the code's schema; the message names it and the fix."""


class DatabaseUnreachableError(DatabaseNotReadyError):
    """The database did not answer (a server starting, restarting or away): unlike a missing or
    old schema, something that may mend itself."""


class SettingsError(Exception):
    """A setting read from the environment is invalid; the message names each by its variable."""
