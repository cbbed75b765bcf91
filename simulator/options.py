"""Scenario options shared by ``narxwatch simulate`` and ``narxwatch-sim``: same names, same help.

A light module on purpose: ``narxwatch-sim`` imports it without loading the service.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Annotated

import typer

from models.errors import InputError
from simulator.physics import FAULT_MODES, PhysicalParameters
from simulator.simulate import EFFECTS

EFFECT_HELP = "Undeclared effect NAME=SIZE (repeatable): " + "; ".join(
    f"{name} [{unit}] {meaning}" for name, (unit, meaning) in EFFECTS.items()
)
Fault = Annotated[str, typer.Option(help=f"Fault mode: {', '.join(FAULT_MODES)}.")]
Magnitude = Annotated[
    float, typer.Option(help="Fault magnitude in percent (positive = stiffness reduction).")
]
Samples = Annotated[int, typer.Option(help="Number of samples per record.", min=1)]
ExcitationStd = Annotated[float, typer.Option(help="Std of the white force excitation x [N].")]
DisturbanceStd = Annotated[
    float, typer.Option(help="Std of the unmeasured white force on mass 1 [N] (white NARX residual).")
]
NoiseStd = Annotated[float, typer.Option(help="Std of white measurement noise on y [m].")]
XNoiseStd = Annotated[float, typer.Option(help="Std of white measurement noise on x [N].")]
NoiseColour = Annotated[
    str | None,
    typer.Option(
        help="Colour the measurement noise by a moving average: coefficients c1,c2,… of 1 + c1·q⁻¹ + …"
    ),
]


def parse_colour(text: str | None) -> tuple[float, ...]:
    """Moving-average coefficients from ``"1.5,1.2,0.9"``; none for None or an empty string."""
    if not text:
        return ()
    try:
        return tuple(float(part) for part in text.split(","))
    except ValueError:
        raise InputError(
            f"--noise-colour {text!r}: write comma-separated numbers, e.g. 1.5,1.2,0.9"
        ) from None


EffectList = Annotated[list[str] | None, typer.Option(help=EFFECT_HELP)]
ParamList = Annotated[
    list[str] | None,
    typer.Option(
        help=f"Physical parameter NAME=VALUE (repeatable): {', '.join(PhysicalParameters.names())}."
    ),
]


def parse_assignments(items: Iterable[str], what: str) -> dict[str, float]:
    """``NAME=VALUE`` strings to floats; anything else is refused with a message saying how."""
    values: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError
            values[name.strip()] = float(value)
        except ValueError:
            raise InputError(f"cannot read {what} {item!r}: write NAME=NUMBER") from None
    return values
