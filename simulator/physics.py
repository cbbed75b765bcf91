"""The monitored 2-DOF structure with a cubic spring, discretised by forward differences (SPEC §1).

    m1·ẍ1 + (k1 + k2)·x1 − k2·x2 + c1·ẋ1 = F + w
    m2·ẍ2 − k2·x1 + k2·x2 + k3·x2³ + c2·ẋ2 = 0

with ẋ[t] ≈ (x[t+1] − x[t])/Ts and ẍ[t] ≈ (x[t+2] − 2x[t+1] + x[t])/Ts². Units: kg, N/m, N/m³,
N·s/m, seconds, metres and newtons. F is the measured excitation x, x2 the measured response y,
w an unmeasured force disturbance.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Literal

import numpy as np

from models.errors import InputError
from recordfiles.quantities import SignalDeclaration
from simulator.temperature import Thermal

FaultMode = Literal["none", "k1", "k2"]
FAULT_MODES: tuple[FaultMode, ...] = ("none", "k1", "k2")
SPRINGS = ("k1", "k2", "k3")  # the stiffnesses temperature acts on (k3 the cubic spring)
# What the rig's records hold, as a structure of it declares them.
EXCITATION = SignalDeclaration("force", "N")
RESPONSE = SignalDeclaration("displacement", "m")


class UnstableSimulationError(InputError):
    """The explicit scheme is, or became, unstable for the requested settings."""


@dataclass(frozen=True)
class PhysicalParameters:
    """Physical parameters; the defaults are the paper's Table 1, read literally (SPEC §1).

    ``ts`` is the discretisation step; the paper uses 6.666·10⁻⁴ s and calls it fs = 1500 Hz.
    """

    m1: float = 10.0
    m2: float = 55.0
    k1: float = 10e3
    k2: float = 90e3
    k3: float = 900e3
    c1: float = 750.0
    c2: float = 300.0
    ts: float = 6.666e-4

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not np.isfinite(value):
                raise InputError(f"parameter {field.name} = {value} is not a finite number")
        for name in ("m1", "m2", "ts"):
            if getattr(self, name) <= 0:
                raise InputError(f"parameter {name} must be positive, got {getattr(self, name)}")
        for name in ("k1", "k2", "k3", "c1", "c2"):
            if getattr(self, name) < 0:
                raise InputError(f"parameter {name} must not be negative, got {getattr(self, name)}")

    @classmethod
    def names(cls) -> list[str]:
        return [field.name for field in dataclasses.fields(cls)]

    def replace(self, **changes: float) -> PhysicalParameters:
        unknown = set(changes) - set(self.names())
        if unknown:
            raise InputError(
                f"unknown parameter {', '.join(sorted(unknown))}; known: {', '.join(self.names())}"
            )
        return dataclasses.replace(self, **changes)

    def with_fault(self, mode: FaultMode, k: float) -> PhysicalParameters:
        """Stiffness k1 or k2 multiplied by (1 − k/100): positive k is a reduction (loosening)."""
        if mode not in FAULT_MODES:
            raise InputError(f"unknown fault mode {mode!r}; choose one of {', '.join(FAULT_MODES)}")
        if mode == "none":
            return self
        if not np.isfinite(k) or k >= 100:
            raise InputError(f"fault magnitude {k} % would remove the spring entirely; use k < 100")
        return self.replace(**{mode: getattr(self, mode) * (1 - k / 100)})

    def at_temperature(self, temperature: float, thermal: Thermal) -> PhysicalParameters:
        """Every spring's stiffness at ``temperature`` (the parameters hold at the reference)."""
        thermal.check(SPRINGS)
        return self.replace(
            **{name: getattr(self, name) * thermal.factor(name, temperature) for name in SPRINGS}
        )

    @cached_property
    def linear_pole_radius(self) -> float:
        """Largest pole modulus of the linearised discrete system about rest."""
        return pole_radius(self)

    @property
    def stable_amplitude(self) -> float:
        """Largest |x2| (m) at which the scheme, linearised with the cubic spring's tangent
        stiffness 3·k3·x2², still has all poles inside the unit circle."""
        return _stable_amplitude(self)


# Kept by value, not on the instance: every scenario built anew (each record a test or a client
# simulates) derives its parameters anew, and this bisection of some sixty polynomial roots costs
# more than simulating a short record. Equal parameters (frozen, hashed by their fields) share it.
@lru_cache(maxsize=1024)
def _stable_amplitude(p: PhysicalParameters) -> float:
    if p.k3 == 0 or p.linear_pole_radius >= 1:
        return np.inf if p.k3 == 0 else 0.0
    low, high = 0.0, 1.0
    while pole_radius(p, 3 * p.k3 * high**2) < 1:
        low, high = high, 2 * high
        if high > 1e6:
            return np.inf
    for _ in range(60):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if pole_radius(p, 3 * p.k3 * middle**2) < 1 else (low, middle)
    return low


def characteristic_polynomial(p: PhysicalParameters, extra_k_mass2: float = 0.0) -> np.ndarray:
    """Coefficients (highest power first) of the discrete characteristic polynomial in q.

    With A1(q) = m1/Ts²·(q−1)² + c1/Ts·(q−1) + k1 + k2 and
    A2(q) = m2/Ts²·(q−1)² + c2/Ts·(q−1) + k2 + extra, eliminating x1 gives A1·A2 − k2².
    """
    a1 = np.array(
        [p.m1 / p.ts**2, -2 * p.m1 / p.ts**2 + p.c1 / p.ts, p.m1 / p.ts**2 - p.c1 / p.ts + p.k1 + p.k2]
    )
    a2 = np.array(
        [
            p.m2 / p.ts**2,
            -2 * p.m2 / p.ts**2 + p.c2 / p.ts,
            p.m2 / p.ts**2 - p.c2 / p.ts + p.k2 + extra_k_mass2,
        ]
    )
    poly = np.polymul(a1, a2)
    poly[-1] -= p.k2**2
    return poly


def pole_radius(p: PhysicalParameters, extra_k_mass2: float = 0.0) -> float:
    return float(np.max(np.abs(np.roots(characteristic_polynomial(p, extra_k_mass2)))))


def check_stable(p: PhysicalParameters) -> None:
    """Refuse a parameter set on which the forward-difference scheme diverges from rest."""
    check_pole_radius(
        p.linear_pole_radius,
        p.ts,
        "for these parameters",
        " (c1, c2 large enough against the stiffnesses and the step); use a smaller Ts or more damping",
    )


def check_pole_radius(radius: float, ts: float, subject: str, remedy: str) -> None:
    """Refuse a discretised system with a pole of modulus ``radius`` ≥ 1 (``subject``, the rig's
    parameters or a chain), saying what makes the explicit scheme stable (``remedy``)."""
    if radius >= 1:
        raise UnstableSimulationError(
            f"the forward-difference scheme is unstable {subject}: a pole of the discretised system "
            f"has modulus {radius:.4f} ≥ 1 at Ts = {ts:g} s. The explicit scheme needs damping to "
            f"dominate{remedy}"
        )
