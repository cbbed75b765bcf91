"""What a signal measures: a quantity from one vocabulary and a unit as the rig states it.

Units are the rig's: a structure declares its excitation's and its response's (``force`` in
``N``, ``acceleration`` in ``m/s²``), and charts and reports label x, y and the residual e with
them. Nothing is assumed where nothing is declared: an undeclared response is drawn as plain "y",
never in the metres of the simulated rig the method was first shown on.

A unit follows the rule of the operating conditions' units (:mod:`recordfiles.conditions`): 1 to
:data:`UNIT_LENGTH` printable characters without spaces, kept in composed form without
surrounding whitespace (:func:`recordfiles.names.normalised_name`), so that "m/s²" typed two ways
is one unit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

from models.errors import InputError
from recordfiles.names import normalised_name

Quantity = Literal[
    "force", "acceleration", "velocity", "displacement", "strain", "voltage", "current", "pressure", "other"
]
QUANTITIES: tuple[str, ...] = get_args(Quantity)
UNIT_LENGTH = 16
UNIT_HELP = f"1 to {UNIT_LENGTH} printable characters without spaces (such as N, m/s², µε or °C)"


def is_unit(unit: str) -> bool:
    """Whether ``unit`` is printable (no control, format or separator characters, so no hidden
    ones), has no space and is 1 to :data:`UNIT_LENGTH` characters long."""
    return 0 < len(unit) <= UNIT_LENGTH and unit.isprintable() and " " not in unit


def checked_unit(unit: str, what: str = "unit") -> str:
    """``unit`` normalised as names are, or ``InputError`` saying what a unit may be."""
    unit = normalised_name(unit, what)
    if not is_unit(unit):
        shown = unit if len(unit) <= 2 * UNIT_LENGTH else unit[: 2 * UNIT_LENGTH] + "…"
        raise InputError(f"the {what} {shown!r} is not allowed: a unit is {UNIT_HELP}")
    return unit


@dataclass(frozen=True)
class SignalDeclaration:
    """What one signal of a structure measures; ``unit`` None when not stated."""

    quantity: Quantity
    unit: str | None = None


def signal_label(symbol: str, declared: SignalDeclaration | None, quantity: bool = True) -> str:
    """An axis or column label for ``symbol`` (x, y, e, e_a1, …) as ``declared``:
    "acceleration y [m/s²]", "y [m/s²]" without the ``quantity`` (or for "other"), plain "y"
    where nothing is declared. The residual e of a response takes the response's declaration."""
    if declared is None:
        return symbol
    # "other" names no quantity: the unit alone says what the signal is.
    named = f"{declared.quantity} {symbol}" if quantity and declared.quantity != "other" else symbol
    return f"{named} [{declared.unit}]" if declared.unit else named
