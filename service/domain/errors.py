"""Errors of the service's logic; the API maps each to its HTTP status."""

from __future__ import annotations


class NotFoundError(LookupError):
    """An id that does not exist, or belongs to another organisation (never say which)."""

    def __init__(self, what: str, identifier: object) -> None:
        super().__init__(f"{what} {identifier} not found")


class ConflictError(RuntimeError):
    """The request is well formed but the state does not allow it."""
