"""NARX terms with readable names.

A term is a product of factors, each a lagged signal raised to a power: ``y[t-2]^3`` or
``y[t-1]*x[t-4]``. The empty product is the constant term ``1``. Beyond polynomials, so that a
model can carry the effects physics puts into real structures, a factor may also be

- a first difference of a signal, ``dy[t-1]`` = y[t-1] − y[t-2] (a velocity, for damping),
  alone or inside ``abs(…)`` or ``sign(…)``: ``sign(dy[t-1])`` is Coulomb friction,
  ``dy[t-1]*abs(dy[t-1])`` quadratic damping;
- ``abs(…)`` or ``sign(…)`` of a plain signal too: ``abs(y[t-1])``, ``sign(x[t-2])``;
- a signed or absolute fractional power with its exponent after a comma,
  ``spow(y[t-1],0.5)`` = |y[t-1]|^0.5·sign(y[t-1]) (a tank's outflow through an orifice) and
  ``apow(dy[t-1],1.5)`` = |dy[t-1]|^1.5;
- an input through a dead zone or backlash of half-width w, ``deadzone(x[t-4],1500)`` =
  x − clip(x, −w, w) and ``backlash(x[t-4],1500)``, the output of a play operator of width 2w
  driven by x (the output stays put until the input has moved w past it, then follows it at
  that distance). Backlash has memory: it is run over the rows a regressor is computed on,
  starting with the play centred on the first value, and forgets that start once the input
  has moved by 2w;
- the Bouc–Wen hysteretic variable of the output, ``boucwen(y[t-2],0.05)`` = z[t-2], with
  dz = dy − β|dy|·z − γ·dy·|z| (Wen 1976, n = 1, A = 1), β = 1/(2w) and γ = r·β for the shape
  r = γ/β after a second comma, ``boucwen(y[t-2],0.05,-1.4)``, 1 when left out. For r > −1 z
  saturates at ±2w/(1 + r) (±w for r = 1); for r < −1 (β + γ < 0) it stiffens as y moves on
  from where it turned, as in Noël and Schoukens' hysteretic benchmark. Bouc–Wen with n = 1 is
  rate-independent and, while y moves one way and z keeps its sign, linear in z along y, so z
  is advanced over each step of y exactly (:func:`bouc_wen_step`), however large the step
  against w. Like backlash it is run over the rows it is computed on from z = 0 (the free run:
  from the record's first sample), and forgets its start as y moves;
- a sinusoid of the sample index t, ``sin(2pi*0.0125*t)`` or ``cos(…)``, its frequency in
  cycles per sample: a periodic disturbance, phase-locked to the record's first sample.

Names parse back to the same term, so a model structure can be written by hand, stored as text
and read again.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numba
import numpy as np

from models.errors import InputError

SIGNALS = ("y", "x", "dy", "dx", "sin", "cos")
FUNCTIONS = ("", "abs", "sign", "spow", "apow", "deadzone", "backlash", "boucwen")
# Functions with a parameter after a comma: the exponent of a power, the half-width of a play.
POWER_LAWS = ("spow", "apow")
INPUT_PLAYS = ("deadzone", "backlash")
# Memory operators on the output, with the level they saturate at as their parameter.
OUTPUT_HYSTERESES = ("boucwen",)
WAVES = ("sin", "cos")
# Beyond these a term cannot describe a physical structure, and its regressor would overflow
# or take unbounded time to build.
MAX_POWER = 9
MAX_LAG = 10_000
_LAGGED = re.compile(
    r"^(?:(?P<function>abs|sign)\((?P<inner>d?[xy])\[t(?:-(?P<inner_lag>\d+))?\]\)"
    r"|(?P<signal>d?[xy])\[t(?:-(?P<lag>\d+))?\])(?:\^(?P<power>\d+))?$"
)
_WITH_PARAMETER = re.compile(
    r"^(?P<function>spow|apow|deadzone|backlash|boucwen)\((?P<signal>d?[xy])\[t(?:-(?P<lag>\d+))?\],"
    r"(?P<parameter>[0-9.eE+-]+)(?:,(?P<shape>[0-9.eE+-]+))?\)(?:\^(?P<power>\d+))?$"
)
_WAVE = re.compile(r"^(?P<wave>sin|cos)\(2pi\*(?P<frequency>[0-9.eE+-]+)\*t\)(?:\^(?P<power>\d+))?$")
Lagged = Callable[[int], np.ndarray]


@dataclass(frozen=True, order=True)
class Factor:
    """One factor of a term: ``function(signal[t-lag])^power``, or a sinusoid of t.

    ``signal`` is y or x, their first differences dy or dx, or sin or cos; ``function`` is ""
    (none), "abs", "sign", a power law "spow" or "apow" of exponent ``parameter`` (power 1),
    on x alone "deadzone" or "backlash" of half-width ``parameter``, on y alone "boucwen"
    of level ``parameter`` and shape ``shape`` (power 1; the shape belongs to it alone); ``frequency``
    (cycles per sample, below 0.5) belongs to sin and cos, whose lag is 0.
    """

    signal: str
    lag: int
    power: int = 1
    function: str = ""
    frequency: float = 0.0
    parameter: float = 0.0
    shape: float = 1.0

    def __post_init__(self) -> None:
        if self.signal not in SIGNALS:
            raise InputError(f"unknown signal {self.signal!r}: a factor uses y, x, dy, dx, sin or cos")
        if self.signal == "y" and self.lag == 0:
            raise InputError("lag 0 of y is not allowed: y needs a lag >= 1")
        if self.signal == "dy" and self.lag == 0:
            raise InputError("lag 0 of dy is not allowed: dy[t-1] = y[t-1] - y[t-2] is the latest")
        if not 0 <= self.lag <= MAX_LAG:
            raise InputError(f"lag {self.lag} of {self.signal} is not allowed: lags run from 0 to {MAX_LAG}")
        if not 1 <= self.power <= MAX_POWER:
            raise InputError(f"power {self.power} is not allowed: powers are >= 1 and at most {MAX_POWER}")
        self._check_function()
        if self.signal in WAVES:
            if self.lag != 0 or not 0.0 < self.frequency < 0.5:
                raise InputError(
                    f"{self.signal}(2pi*f*t) needs 0 < f < 0.5 cycles per sample, got {self.frequency}"
                )
        elif self.frequency:
            raise InputError(f"only sin and cos have a frequency, not {self.signal}")

    def _check_function(self) -> None:
        if self.function not in FUNCTIONS:
            raise InputError(f"unknown function {self.function!r}: use {', '.join(FUNCTIONS[1:])}")
        if self.function and self.signal in WAVES:
            raise InputError(f"{self.function}(…) applies to y, x, dy or dx, not to {self.signal}")
        if self.function in INPUT_PLAYS and self.signal != "x":
            raise InputError(f"{self.function}(…) applies to the input x, not to {self.signal}")
        if self.function in OUTPUT_HYSTERESES and self.signal != "y":
            raise InputError(f"{self.function}(…) applies to the output y, not to {self.signal}")
        if self.function in ("sign", *POWER_LAWS, *OUTPUT_HYSTERESES) and self.power > 1:
            raise InputError(
                f"a power of {self.function}(…) is not allowed: write the exponent inside "
                "(sign(…) is its own power)"
            )
        if self.function in POWER_LAWS and not 0.0 < self.parameter <= MAX_POWER:
            raise InputError(
                f"{self.function}(…) needs an exponent 0 < p <= {MAX_POWER}, got {self.parameter}"
            )
        if self.function in (*INPUT_PLAYS, *OUTPUT_HYSTERESES) and not (0.0 < self.parameter < math.inf):
            raise InputError(f"{self.function}(…) needs a finite half-width w > 0, got {self.parameter}")
        with_parameter = POWER_LAWS + INPUT_PLAYS + OUTPUT_HYSTERESES
        if self.parameter and self.function not in with_parameter:
            raise InputError(f"only {', '.join(with_parameter)} take a parameter")
        if self.shape != 1.0 and self.function not in OUTPUT_HYSTERESES:
            raise InputError(f"only {', '.join(OUTPUT_HYSTERESES)} take a shape, a second parameter")
        if not math.isfinite(self.shape):
            raise InputError(f"{self.function}(…) needs a finite shape, got {self.shape}")

    @property
    def name(self) -> str:
        if self.signal in WAVES:
            base = f"{self.signal}(2pi*{self.frequency!r}*t)"
        else:
            base = f"{self.signal}[t]" if self.lag == 0 else f"{self.signal}[t-{self.lag}]"
            if self.function in (*POWER_LAWS, *INPUT_PLAYS, *OUTPUT_HYSTERESES):
                shape = "" if self.shape == 1.0 else f",{self.shape!r}"
                base = f"{self.function}({base},{self.parameter!r}{shape})"
            elif self.function:
                base = f"{self.function}({base})"
        return base if self.power == 1 else f"{base}^{self.power}"

    @property
    def reach(self) -> int:
        """How many samples back the factor reads: its lag, one more for a difference."""
        return self.lag + (self.signal in ("dy", "dx"))

    @property
    def autoregressive(self) -> bool:
        """Whether the factor reads the output, so that a simulation must compute it as it runs."""
        return self.signal in ("y", "dy")

    @property
    def plain(self) -> bool:
        return self.signal in ("y", "x")

    def values(self, lagged_y: Lagged, lagged_x: Lagged, times: np.ndarray) -> np.ndarray:
        """The factor over the rows whose sample indices are ``times``; ``lagged_y(k)`` and
        ``lagged_x(k)`` give y[t−k] and x[t−k] over the same rows."""
        if self.signal in WAVES:
            wave = np.sin if self.signal == "sin" else np.cos
            base = wave(2.0 * math.pi * self.frequency * times)
        else:
            lagged = lagged_y if self.signal in ("y", "dy") else lagged_x
            base = lagged(self.lag)
            if not self.plain:
                base = base - lagged(self.lag + 1)
            base = self._transformed(base)
        values = base
        # Repeated products: ~100× faster than numpy's general pow for small powers.
        for _ in range(self.power - 1):
            values = values * base
        return values

    def _transformed(self, base: np.ndarray) -> np.ndarray:
        if self.function == "abs":
            return np.abs(base)
        if self.function == "sign":
            return np.sign(base)
        if self.function == "spow":
            return np.sign(base) * np.abs(base) ** self.parameter
        if self.function == "apow":
            return np.abs(base) ** self.parameter
        if self.function == "deadzone":
            return base - np.clip(base, -self.parameter, self.parameter)
        if self.function == "backlash":
            return play(np.ascontiguousarray(base, dtype=np.float64), self.parameter)
        if self.function == "boucwen":
            return bouc_wen(np.ascontiguousarray(base, dtype=np.float64), self.parameter, self.shape)
        return base


@numba.njit(cache=True, nogil=True)
def bouc_wen(series: np.ndarray, level: float, shape: float) -> np.ndarray:
    """The Bouc–Wen variable of a series (n = 1, β = 1/(2·level), γ = shape·β), from z = 0."""
    out = np.zeros_like(series)
    for t in range(1, series.size):
        out[t] = bouc_wen_step(out[t - 1], series[t] - series[t - 1], level, shape)
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def bouc_wen_step(z: float, step: float, level: float, shape: float) -> float:
    """z after the series moves by ``step``: dz = dy − β|dy|·z − γ·dy·|z| solved exactly along
    a monotone path, β = 1/(2·level) and γ = shape·β.

    In s = z·sign(dy), along the distance d moved, ds/dd = 1 − c·s with c = β + γ while s ≥ 0
    (the move drives z away from zero) and c = β − γ while s < 0 (back towards it): linear in
    each part, so s + (1 − c·s)·(1 − e^(−c·d))/c until s reaches zero, and on from there. A
    forward difference, z + Δ − β|Δ|z − γΔ|z|, is its first order: it overshoots the level once a
    step exceeds it, so a search would have to keep the level above the record's steps."""
    distance = abs(step)
    if distance == 0.0:
        return z
    direction = 1.0 if step > 0.0 else -1.0
    beta = 0.5 / level
    s = z * direction
    if s < 0.0:
        rate = beta * (1.0 - shape)
        # How far the series moves before s reaches zero: never where s runs away (1 − c·s ≤ 0).
        pull = 1.0 - rate * s
        to_zero = np.inf if pull <= 0.0 else -s if rate == 0.0 else np.log(pull) / rate
        if to_zero > distance:
            return direction * (s + pull * _along(rate, distance))
        distance -= to_zero
        s = 0.0
    rate = beta * (1.0 + shape)
    return direction * (s + (1.0 - rate * s) * _along(rate, distance))


@numba.njit(cache=True, nogil=True, inline="always")
def _along(rate: float, distance: float) -> float:
    """(1 − e^(−rate·distance))/rate, which is ``distance`` where the rate is zero."""
    return distance if rate == 0.0 else -np.expm1(-rate * distance) / rate


@numba.njit(cache=True, nogil=True)
def play(series: np.ndarray, half_width: float) -> np.ndarray:
    """The play (backlash) operator: out[0] = series[0], then out[t] stays at out[t−1] unless
    series[t] has moved more than ``half_width`` from it, and then trails it at that distance."""
    out = np.empty_like(series)
    if series.size == 0:
        return out
    out[0] = series[0]
    for t in range(1, series.size):
        out[t] = min(max(out[t - 1], series[t] - half_width), series[t] + half_width)
    return out


@dataclass(frozen=True)
class Term:
    """A monomial of lagged signals; ``factors`` is kept sorted and merged."""

    factors: tuple[Factor, ...] = ()

    @classmethod
    def of(cls, factors: Iterable[Factor]) -> Term:
        powers: dict[tuple[str, int, str, float, float, float], int] = {}
        for factor in factors:
            key = (
                factor.signal,
                factor.lag,
                factor.function,
                factor.frequency,
                factor.parameter,
                factor.shape,
            )
            powers[key] = powers.get(key, 0) + factor.power
        # y before x, then by lag: matches how the paper writes its regressors.
        ordered = sorted(
            powers.items(),
            key=lambda item: (
                SIGNALS.index(item[0][0]),
                item[0][1],
                FUNCTIONS.index(item[0][2]),
                item[0][3],
                item[0][4],
                item[0][5],
            ),
        )
        return cls(
            tuple(
                Factor(signal, lag, power, function, frequency, parameter, shape)
                for (signal, lag, function, frequency, parameter, shape), power in ordered
            )
        )

    @classmethod
    def parse(cls, name: str) -> Term:
        """Read a term from its name, e.g. ``"y[t-2]^3"``, ``"y[t-1]*x[t-4]"`` or ``"1"``."""
        text = name.replace(" ", "")
        if text == "1":
            return cls()
        factors = [_parse_factor(part, name) for part in _split_product(text)]
        return cls.of(factors)

    @property
    def name(self) -> str:
        return "*".join(f.name for f in self.factors) if self.factors else "1"

    @property
    def degree(self) -> int:
        return sum(f.power for f in self.factors)

    @property
    def max_lag(self) -> int:
        return max((f.reach for f in self.factors), default=0)

    def __str__(self) -> str:
        return self.name


def _split_product(text: str) -> list[str]:
    # "*" also appears inside sin(2pi*f*t): split only outside parentheses.
    parts, depth, start = [], 0, 0
    for i, char in enumerate(text):
        depth += (char == "(") - (char == ")")
        if char == "*" and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    parts.append(text[start:])
    return parts


def _parse_factor(part: str, name: str) -> Factor:
    if wave := _WAVE.match(part):
        try:
            frequency = float(wave["frequency"])
        except ValueError:
            raise InputError(f"cannot read term {name!r}: {wave['frequency']!r} is not a frequency") from None
        return Factor(wave["wave"], 0, int(wave["power"] or 1), frequency=frequency)
    if with_parameter := _WITH_PARAMETER.match(part):
        try:
            parameter, shape = (float(with_parameter[key] or 1.0) for key in ("parameter", "shape"))
        except ValueError:
            raise InputError(
                f"cannot read term {name!r}: {with_parameter['parameter']!r} or "
                f"{with_parameter['shape'] or ''!r} is not a number"
            ) from None
        return Factor(
            with_parameter["signal"],
            int(with_parameter["lag"] or 0),
            int(with_parameter["power"] or 1),
            with_parameter["function"],
            parameter=parameter,
            shape=shape,
        )
    lagged = _LAGGED.match(part)
    if lagged is None:
        raise InputError(
            f"cannot read term {name!r}: write factors like y[t-1], y[t-2]^3, x[t-4], dy[t-1], "
            "sign(dy[t-1]), abs(dy[t-1]), spow(y[t-1],0.5), deadzone(x[t-4],100), boucwen(y[t-2],0.05) or "
            "sin(2pi*0.01*t), joined by '*', or '1' for the constant"
        )
    power = int(lagged["power"] or 1)
    if lagged["function"]:
        return Factor(lagged["inner"], int(lagged["inner_lag"] or 0), power, lagged["function"])
    return Factor(lagged["signal"], int(lagged["lag"] or 0), power)


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


def max_degree(terms: Sequence[Term]) -> int:
    """The highest degree among ``terms`` (1 at least): what bounds a record's values
    (:func:`models.signals.magnitude_limit`)."""
    return max((t.degree for t in terms), default=1) or 1


def max_lag(terms: Sequence[Term]) -> int:
    """The number of initial samples a record must supply before the first prediction."""
    return max(term.max_lag for term in terms)


class OverTerms:
    """What a model over ``terms`` asks of a record and how it names its terms, for the models'
    dataclasses to inherit (their own field ``terms`` is what this reads)."""

    terms: tuple[Term, ...]

    @property
    def max_lag(self) -> int:
        return max_lag(self.terms)

    @property
    def term_names(self) -> list[str]:
        return [term.name for term in self.terms]


def regressor_matrix(
    terms: Sequence[Term], x: np.ndarray, y: np.ndarray, lag: int | None = None, t0: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Regressor matrix Φ and target for one record.

    Row ``r`` holds φ[t] for t = L + r, with L = ``lag`` (default: the largest lag of the
    terms), so Φ has N − L rows and one column per term; the target is y[L:]. ``t0`` is the
    sample index of the record's first sample in the time base of sinusoidal terms.
    """
    L = max_lag(terms) if lag is None else lag
    n = len(y)
    times = np.arange(t0 + L, t0 + n, dtype=np.float64)

    def lagged_y(k: int) -> np.ndarray:
        return y[L - k : n - k]

    def lagged_x(k: int) -> np.ndarray:
        return x[L - k : n - k]

    cache: dict[Factor, np.ndarray] = {}
    Phi = np.empty((n - L, len(terms)))
    for col, term in enumerate(terms):
        column = np.ones(n - L)
        for factor in term.factors:
            values = cache.get(factor)
            if values is None:
                values = cache[factor] = factor.values(lagged_y, lagged_x, times)
            column = column * values
        Phi[:, col] = column
    return Phi, y[L:]


def record_origins(t0: int | Sequence[int], count: int) -> list[int]:
    """Where each of ``count`` records starts in the time base of sinusoidal terms: ``t0`` for
    every one, or ``t0[i]`` for record i."""
    origins = [t0] * count if isinstance(t0, int) else list(t0)
    if len(origins) != count:
        raise InputError(f"{len(origins)} time origins given for {count} records")
    return origins


def stacked_regressors(
    terms: Sequence[Term],
    records: Sequence[tuple[np.ndarray, np.ndarray]],
    lag: int | None = None,
    t0: int | Sequence[int] = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`regressor_matrix` of several records stacked, so that no lag reaches across the
    boundary between two: Φ, the target and each record's first row (with the end as last entry).

    ``t0`` is one sample index for every record, or one a record: where each starts in the time
    base of sinusoidal terms.
    """
    pairs = zip(records, record_origins(t0, len(records)), strict=True)
    blocks = [regressor_matrix(terms, x, y, lag, origin) for (x, y), origin in pairs]
    Phi = np.vstack([block[0] for block in blocks])
    target = np.concatenate([block[1] for block in blocks])
    starts = np.cumsum([0] + [block[1].size for block in blocks])
    return Phi, target, starts
