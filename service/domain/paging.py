"""A page of a cursor-paginated listing, as the domain returns it and a router answers it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Generic, TypeVar

Item = TypeVar("Item")
Cursor = TypeVar("Cursor", str, int)


@dataclass(frozen=True)
class Page(Generic[Item, Cursor]):
    """``items`` in the listing's order; ``next_cursor`` None on the last page."""

    items: list[Item]
    next_cursor: Cursor | None
