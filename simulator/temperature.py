"""Temperature and stiffness: springs that soften as they warm, and the daily and seasonal cycles.

Bridge natural frequencies move by about 5 % over a year with temperature, enough to swamp a 3 %
stiffness fault. The simulator states the effect per spring, linear in the temperature about a
reference, k(T) = k·(1 + c·(T − T_ref)) with c in %/°C, and draws each record's temperature from
its acquisition time, so that a baseline trained in one season can be tested in the next.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

from models.errors import InputError

REFERENCE_TEMPERATURE = 20.0  # °C: the temperature at which the stated stiffnesses hold
DEFAULT_COEFFICIENT = -0.5  # %/°C for a spring whose coefficient is not stated
DAILY_PEAK_HOUR = 15.0  # the warmest hour of the day, in the acquisition time's own zone
SEASONAL_PEAK_DAY = 200.5  # noon on 20 July (days from 1 January, 0:00), the warmest of a northern year
DAYS_PER_YEAR = 365.2425


@dataclass(frozen=True)
class Thermal:
    """Stiffness against temperature: spring NAME has k(T) = k·(1 + c/100·(T − reference)), with c
    from ``coefficients`` [%/°C] or, for a spring not named there, ``default``."""

    coefficients: Mapping[str, float] = field(default_factory=dict)
    default: float = DEFAULT_COEFFICIENT
    reference: float = REFERENCE_TEMPERATURE

    def check(self, springs: Iterable[str]) -> None:
        """Refuse coefficients of springs the structure does not have, or that are not finite."""
        springs = list(springs)
        unknown = sorted(set(self.coefficients) - set(springs))
        if unknown:
            raise InputError(
                f"--thermal-coefficient names no spring of this structure: {', '.join(unknown)}; "
                f"its springs are {', '.join(springs)}"
            )
        for name, value in {
            **self.coefficients,
            "default": self.default,
            "reference": self.reference,
        }.items():
            if not math.isfinite(value):
                raise InputError(f"thermal coefficient {name} must be a finite number, got {value}")

    def factor(self, spring: str, temperature: float) -> float:
        """k(T)/k for one spring; a spring that would lose all its stiffness is refused."""
        coefficient = self.coefficients.get(spring, self.default)
        factor = 1 + coefficient / 100 * (temperature - self.reference)
        if not (math.isfinite(temperature) and factor > 0):
            raise InputError(
                f"at {temperature:g} °C spring {spring} (coefficient {coefficient:g} %/°C about "
                f"{self.reference:g} °C) would have no stiffness left; choose a temperature nearer "
                f"{self.reference:g} °C or a smaller coefficient"
            )
        return factor


@dataclass(frozen=True)
class TemperatureCycle:
    """Air temperature over the day and the year:

        T(t) = mean + daily·cos(2π·(hour − 15)/24) + seasonal·cos(2π·(day − 200.5)/365.2425)

    with ``hour`` the time of day in the acquisition time's own zone and ``day`` the time since
    1 January, 0:00, in days: warmest at 15:00 and at noon on 20 July (a negative seasonal
    amplitude: the southern hemisphere). The amplitudes are half the peak-to-peak swings, so a
    year spans mean ± (|daily| + |seasonal|).
    """

    mean: float
    daily: float = 0.0
    seasonal: float = 0.0

    def __post_init__(self) -> None:
        for name in ("mean", "daily", "seasonal"):
            if not math.isfinite(getattr(self, name)):
                raise InputError(f"temperature {name} must be a finite number, got {getattr(self, name)}")

    @property
    def extremes(self) -> tuple[float, float]:
        """The lowest and highest temperature the cycle reaches."""
        swing = abs(self.daily) + abs(self.seasonal)
        return self.mean - swing, self.mean + swing

    def at(self, moment: dt.datetime) -> float:
        """The temperature at an acquisition time."""
        hour = moment.hour + moment.minute / 60 + (moment.second + moment.microsecond / 1e6) / 3600
        day = moment.timetuple().tm_yday - 1 + hour / 24
        return (
            self.mean
            + self.daily * math.cos(2 * math.pi * (hour - DAILY_PEAK_HOUR) / 24)
            + self.seasonal * math.cos(2 * math.pi * (day - SEASONAL_PEAK_DAY) / DAYS_PER_YEAR)
        )
