"""Path and query parameter types shared by the routers."""

from __future__ import annotations

import datetime as dt
from typing import Annotated

from fastapi import Path

from models.errors import InputError

# Bounded so that no id can overflow a 64-bit database integer.
IdPath = Annotated[int, Path(ge=1, le=2**62)]


def require_timezone(value: dt.datetime | None, name: str) -> dt.datetime | None:
    """A naive timestamp is ambiguous across sites: refuse it rather than guess a zone."""
    if value is not None and value.tzinfo is None:
        raise InputError(f"{name} needs a timezone, e.g. 2026-11-21T10:00:00Z")
    return value
