"""Operating conditions: named scalar variables a record was acquired under, with their units.

A bridge's natural frequencies move with its temperature by more than a small stiffness fault
moves them, so a record states what it was measured under (temperature in °C, excitation level,
speed, …) for models and people to take into account. A condition is a name, a finite value and
an optional unit; every way into the service (JSON fields, CSV comment lines, NPZ scalar
members) ends in :func:`checked_conditions`, so that one rule holds for all of them:

- a name is a lowercase letter followed by at most 31 lowercase letters, digits or underscores,
  and not ``x``, ``y`` or ``fs`` (the signals and the sampling rate). One spelling only, so that
  ``Temperature`` and ``temperature`` can never be two variables of one structure's records;
- a value is a finite number;
- a unit, when given, is 1 to 16 printable characters without spaces (``°C``, ``m/s``, ``%``;
  no control, format or separator characters, so none that cannot be seen); no unit is implied
  for any name;
- a record carries at most :data:`MAX_CONDITIONS` conditions, each name once.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Any

from models.errors import InputError
from recordfiles.names import normalised_name
from recordfiles.quantities import UNIT_HELP, is_unit

MAX_CONDITIONS = 16
NAME_LENGTH = 32
NAME_RULE = re.compile(rf"[a-z][a-z0-9_]{{0,{NAME_LENGTH - 1}}}")
RESERVED = ("x", "y", "fs")
NAME_HELP = (
    f"a condition's name is a lowercase letter followed by at most {NAME_LENGTH - 1} lowercase letters, "
    "digits or underscores (such as temperature or excitation_level)"
)


@dataclass(frozen=True)
class Condition:
    """One operating variable of a record: ``temperature`` = 12.5 ``°C``; ``unit`` None when not stated."""

    name: str
    value: float
    unit: str | None = None


def as_conditions(rows: Iterable[Any]) -> list[Condition]:
    """The conditions stored rows hold (anything with a name, a value and a unit: a stored
    record's condition rows)."""
    return [Condition(row.name, row.value, row.unit) for row in rows]


def checked_conditions(conditions: Iterable[Condition]) -> tuple[Condition, ...]:
    """The conditions sorted by name, their names normalised (``recordfiles.names``), after checking
    each against the rules above.

    Counting stops at one past the limit, so an endless list costs no more than a short one.
    """
    seen: dict[str, Condition] = {}
    for condition in conditions:
        if len(seen) == MAX_CONDITIONS:
            raise too_many_conditions()
        name = normalised_name(condition.name, "condition name")
        condition = replace(condition, name=name)
        if name in seen:
            raise InputError(f"the condition {_shown(name)} is given twice; give each condition once")
        check_condition(condition)
        seen[name] = condition
    return tuple(seen[name] for name in sorted(seen))


def too_many_conditions() -> InputError:
    return InputError(f"a record may carry at most {MAX_CONDITIONS} conditions; this one has more")


def check_condition(condition: Condition) -> None:
    """Refuse a condition that breaks the rules of the module's docstring."""
    name, value, unit = condition.name, condition.value, condition.unit
    check_name(name)
    if not math.isfinite(value):
        raise InputError(f"the condition {name!r} is {value}; a condition's value must be a finite number")
    if unit is not None and not is_unit(unit):
        raise InputError(
            f"the unit {_shown(unit)} of condition {name!r} is not allowed: a unit is {UNIT_HELP}"
        )


def check_name(name: str) -> None:
    """Refuse a name that breaks the naming rule, or that names a signal or the sampling rate."""
    if not NAME_RULE.fullmatch(name):
        raise InputError(f"the condition name {_shown(name)} is not allowed: {NAME_HELP}")
    if name in RESERVED:
        raise InputError(
            f"{name!r} cannot name a condition: x, y and fs are the record's signals and sampling rate"
        )


def _shown(text: str) -> str:
    """``text`` quoted for a message, cut short: a refused name can be as long as a body."""
    return repr(text if len(text) <= 2 * NAME_LENGTH else text[: 2 * NAME_LENGTH] + "…")
