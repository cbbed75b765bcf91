"""Path and query parameter types shared by the routers."""

from __future__ import annotations

import datetime as dt
from typing import Annotated

from fastapi import Path

from models.errors import InputError
from service.schemas import MAX_ID

IdPath = Annotated[int, Path(ge=1, le=MAX_ID)]


def utc(value: dt.datetime | None, name: str) -> dt.datetime | None:
    """The time in UTC. A naive timestamp is ambiguous across sites: refused, not guessed."""
    if value is None:
        return None
    if value.tzinfo is None:
        raise InputError(f"{name} needs a timezone, e.g. 2026-11-21T10:00:00Z")
    try:
        return value.astimezone(dt.UTC)
    except OverflowError:
        raise InputError(f"{name} lies outside the years 1 to 9999 once converted to UTC") from None
