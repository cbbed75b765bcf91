"""Polynomial NARX terms with readable names.

A term is a product of lagged signals raised to powers, for example ``y[t-2]^3`` or
``y[t-1]*x[t-4]``. The empty product is the constant term ``1``. Names parse back to the
same term, so a model structure can be written by hand, stored as text and read again.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from models.errors import InputError

SIGNALS = ("y", "x")
# Beyond these a term cannot describe a physical structure, and its regressor would overflow
# or take unbounded time to build.
MAX_POWER = 9
MAX_LAG = 10_000
_FACTOR = re.compile(r"^(?P<signal>[xy])\[t(?:-(?P<lag>\d+))?\](?:\^(?P<power>\d+))?$")


@dataclass(frozen=True, order=True)
class Factor:
    """One lagged signal raised to a power: ``signal[t-lag]^power``."""

    signal: str
    lag: int
    power: int = 1

    def __post_init__(self) -> None:
        if self.signal not in SIGNALS:
            raise InputError(f"unknown signal {self.signal!r}: a factor uses 'y' or 'x'")
        if self.signal == "y" and self.lag == 0:
            raise InputError("lag 0 of y is not allowed: y needs a lag >= 1")
        if not 0 <= self.lag <= MAX_LAG:
            raise InputError(f"lag {self.lag} of {self.signal} is not allowed: lags run from 0 to {MAX_LAG}")
        if not 1 <= self.power <= MAX_POWER:
            raise InputError(f"power {self.power} is not allowed: powers are >= 1 and at most {MAX_POWER}")

    @property
    def name(self) -> str:
        base = f"{self.signal}[t]" if self.lag == 0 else f"{self.signal}[t-{self.lag}]"
        return base if self.power == 1 else f"{base}^{self.power}"


@dataclass(frozen=True)
class Term:
    """A monomial of lagged signals; ``factors`` is kept sorted and merged."""

    factors: tuple[Factor, ...] = ()

    @classmethod
    def of(cls, factors: Iterable[Factor]) -> Term:
        powers: dict[tuple[str, int], int] = {}
        for factor in factors:
            key = (factor.signal, factor.lag)
            powers[key] = powers.get(key, 0) + factor.power
        # y before x, then by lag: matches how the paper writes its regressors.
        ordered = sorted(powers.items(), key=lambda item: (SIGNALS.index(item[0][0]), item[0][1]))
        return cls(tuple(Factor(signal, lag, power) for (signal, lag), power in ordered))

    @classmethod
    def parse(cls, name: str) -> Term:
        """Read a term from its name, e.g. ``"y[t-2]^3"``, ``"y[t-1]*x[t-4]"`` or ``"1"``."""
        text = name.replace(" ", "")
        if text == "1":
            return cls()
        factors = []
        for part in text.split("*"):
            match = _FACTOR.match(part)
            if match is None:
                raise InputError(
                    f"cannot read term {name!r}: write factors like y[t-1], y[t-2]^3 or x[t-4], "
                    "joined by '*', or '1' for the constant"
                )
            factors.append(Factor(match["signal"], int(match["lag"] or 0), int(match["power"] or 1)))
        return cls.of(factors)

    @property
    def name(self) -> str:
        return "*".join(f.name for f in self.factors) if self.factors else "1"

    @property
    def degree(self) -> int:
        return sum(f.power for f in self.factors)

    @property
    def max_lag(self) -> int:
        return max((f.lag for f in self.factors), default=0)

    def __str__(self) -> str:
        return self.name


def parse_terms(names: Iterable[str | Term]) -> tuple[Term, ...]:
    """Terms from names (or terms), refusing an empty list and duplicates."""
    terms = tuple(n if isinstance(n, Term) else Term.parse(n) for n in names)
    if not terms:
        raise InputError("a model needs at least one term")
    seen: set[Term] = set()
    for term in terms:
        if term in seen:
            raise InputError(f"term {term.name} is listed twice")
        seen.add(term)
    return terms


def max_lag(terms: Sequence[Term]) -> int:
    """The number of initial samples a record must supply before the first prediction."""
    return max(term.max_lag for term in terms)


def regressor_matrix(
    terms: Sequence[Term], x: np.ndarray, y: np.ndarray, lag: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Regressor matrix Φ and target for one record.

    Row ``r`` holds φ[t] for t = L + r, with L = ``lag`` (default: the largest lag of the
    terms), so Φ has N − L rows and one column per term; the target is y[L:].
    """
    L = max_lag(terms) if lag is None else lag
    n = len(y)
    signals = {"y": y, "x": x}
    powers: dict[Factor, np.ndarray] = {}
    Phi = np.empty((n - L, len(terms)))
    for col, term in enumerate(terms):
        column = np.ones(n - L)
        for factor in term.factors:
            values = powers.get(factor)
            if values is None:
                window = signals[factor.signal][L - factor.lag : n - factor.lag]
                values = window
                # Repeated products: ~100× faster than numpy's general pow for small powers.
                for _ in range(factor.power - 1):
                    values = values * window
                powers[factor] = values
            column = column * values
        Phi[:, col] = column
    return Phi, y[L:]
