"""Scenario options shared by ``narxwatch simulate`` and ``narxwatch-sim``: same names, same help.

A light module on purpose: ``narxwatch-sim`` imports it without loading the service.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Annotated

import typer

from models.errors import InputError
from simulator.chain import DISTURBANCE_STD, MAX_MASSES, RESPONSES, ChainParameters
from simulator.physics import FAULT_MODES, PhysicalParameters
from simulator.simulate import EFFECTS
from simulator.study import StudySettings
from simulator.temperature import DEFAULT_COEFFICIENT, REFERENCE_TEMPERATURE

# The chain's defaults: each mode damped enough for the explicit scheme up to 5 masses or more
# (lowest 3.2 Hz, highest 21.6 Hz for five).
MASS, STIFFNESS, DAMPING = 10.0, 50e3, 300.0

EFFECT_HELP = "Undeclared effect NAME=SIZE (repeatable): " + "; ".join(
    f"{name} [{unit}] {meaning}" for name, (unit, meaning) in EFFECTS.items()
)
Fault = Annotated[
    str,
    typer.Option(help=f"Fault mode: {', '.join(FAULT_MODES)}; for the chain, any spring k1 … k(n+1)."),
]
Magnitude = Annotated[
    float, typer.Option(help="Fault magnitude in percent (positive = stiffness reduction).")
]
Samples = Annotated[int, typer.Option(help="Number of samples per record.", min=1)]
ExcitationStd = Annotated[float, typer.Option(help="Std of the white force excitation x [N].")]
DisturbanceStd = Annotated[
    float | None,
    typer.Option(
        help="Std of the unmeasured white force on mass 1 [N] (white NARX residual). Default: the rig's "
        f"{StudySettings().disturbance_std:g} N, as in the paper; none on a chain (--masses), whose noise is "
        "its sensors'.",
    ),
]


def disturbance_level(given: float | None, chain: bool) -> float:
    """--disturbance-std as given, or else the structure's own: a ``chain``'s or the rig's."""
    if given is not None:
        return given
    return DISTURBANCE_STD if chain else StudySettings().disturbance_std


NoiseStd = Annotated[float, typer.Option(help="Std of white measurement noise on y [m].")]
XNoiseStd = Annotated[float, typer.Option(help="Std of white measurement noise on x [N].")]
NoiseShare = Annotated[
    float | None,
    typer.Option(
        help="The chain's sensor noise: white noise on x and on each response channel, this share of the "
        "signal's RMS when healthy and noise-free (0.01 for 1 %), the same floor whatever the fault.",
    ),
]
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


# --- Temperature, measured channels and the n-mass chain ----------------------------------------

Temperature = Annotated[
    float | None,
    typer.Option(
        help="Temperature of the structure [°C]; springs stiffen as it falls (see --thermal-coefficient). "
        "Default: none, the stated stiffnesses."
    ),
]
ThermalList = Annotated[
    list[str] | None,
    typer.Option(
        "--thermal-coefficient",
        help=f"Stiffness change of spring NAME per °C about {REFERENCE_TEMPERATURE:g} °C [%/°C], "
        f"NAME=VALUE (repeatable): k(T) = k·(1 + VALUE/100·(T − {REFERENCE_TEMPERATURE:g})). Springs not "
        f"named change by {DEFAULT_COEFFICIENT:g} %/°C. The rig's springs are k1, k2, k3 (cubic); the "
        "chain's k1 … k(n+1).",
    ),
]
Outputs = Annotated[
    str | None,
    typer.Option(
        help="Measured masses: 'all' or numbers such as 1,3,5, each a response channel y1, y3, y5. The rig "
        "measures mass 2 alone by default (the channel y); 'both' (or 'all') gives y1, y2. The chain "
        "measures all its masses by default."
    ),
]
Masses = Annotated[
    int | None,
    typer.Option(
        min=1,
        max=MAX_MASSES,
        help="Simulate a chain of this many masses in series (wall–k1–m1–k2–…–mn–k(n+1)–wall, the force "
        "on mass 1, a damper from each mass to ground) instead of the 2-DOF rig.",
    ),
]
MassValues = Annotated[
    str | None,
    typer.Option("--mass", help=f"Chain masses [kg]: one for all or n, comma-separated ({MASS:g})."),
]
StiffnessValues = Annotated[
    str | None,
    typer.Option(
        "--stiffness",
        help=f"Chain springs [N/m]: one for k1 … kn, n values, or n + 1 with the far wall's ({STIFFNESS:g}).",
    ),
]
DampingValues = Annotated[
    str | None,
    typer.Option("--damping", help=f"Chain dampers to ground [N·s/m]: one for all or n ({DAMPING:g})."),
]
CubicValues = Annotated[
    str | None,
    typer.Option(
        "--cubic",
        help="Cubic parts of the chain's springs [N/m³], force kc·d³ at elongation d: one for k1 … kn, n, or "
        "n + 1 values, e.g. 0,0,0,0,1e6 (none).",
    ),
]
ResponseOption = Annotated[
    str | None,
    typer.Option(
        "--response", help=f"What the chain's sensors measure: {', '.join(RESPONSES)} (displacement)."
    ),
]


def parse_numbers(text: str, option: str) -> list[float]:
    """``"10"`` or ``"10,20,30"`` to numbers, with a message saying how to write them."""
    try:
        return [float(part) for part in text.split(",")]
    except ValueError:
        raise InputError(
            f"{option} {text!r}: write one number or comma-separated numbers, e.g. 10,20,30"
        ) from None


def parse_outputs(text: str | None, masses: int) -> tuple[int, ...] | None:
    """Measured masses from ``--outputs``: None for the structure's default, all for 'all'/'both'."""
    if text is None:
        return None
    if text.strip().lower() in ("all", "both"):
        return tuple(range(1, masses + 1))
    try:
        return tuple(int(part) for part in text.split(","))
    except ValueError:
        raise InputError(f"--outputs {text!r}: write 'all' or mass numbers such as 1,3,5") from None


@dataclass(frozen=True)
class ChainOptions:
    """The chain's options as given (None: not given); :meth:`parameters` checks them."""

    masses: int | None = None
    mass: str | None = None
    stiffness: str | None = None
    damping: str | None = None
    cubic: str | None = None
    response: str | None = None

    def parameters(self) -> ChainParameters | None:
        """The chain's parameters, or None for the rig; chain options without --masses are refused."""
        given = {
            name: value
            for name, value in dataclasses.asdict(self).items()
            if name != "masses" and value is not None
        }
        if self.masses is None:
            if given:
                options = ", ".join(f"--{name}" for name in given)
                raise InputError(
                    f"{options}: options of the chain, which needs its number of masses: give --masses N"
                )
            return None
        return ChainParameters.build(
            self.masses,
            parse_numbers(self.mass or str(MASS), "--mass"),
            parse_numbers(self.stiffness or str(STIFFNESS), "--stiffness"),
            parse_numbers(self.damping or str(DAMPING), "--damping"),
            parse_numbers(self.cubic or "0", "--cubic"),
        )
