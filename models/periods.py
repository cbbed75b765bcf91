"""The output noise of a periodic experiment, from the spread between its periods.

When the excitation x repeats M times with period P and the system has reached its steady state,
the output of period m is y_m[t] = y₀[t] + v_m[t]: the same response y₀ every period, plus a
noise v that does not repeat (measurement noise, and process noise however it enters). Without any
model (Pintelon & Schoukens, *System Identification: A Frequency Domain Approach*, 2nd ed., 2012,
§2.4), its variance is

    σ̂² = 1/(P(M − 1)) Σ_t Σ_m (y_m[t] − ȳ[t])²,   ȳ[t] = (1/M) Σ_m y_m[t],

with P(M − 1) degrees of freedom. No model driven by x alone can simulate y over such records
with a mean square error below σ² on average: σ̂ is the floor of every free-run RMS there, and
√(RMS² − σ̂²) is what a model leaves of y₀.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

MIN_PERIOD = 64  # samples: shorter repeats are a slow sine's, not an experiment's design
# x repeats when its periods differ from their mean by at most this RMS, relative to x's: the
# measured inputs of the Wiener–Hammerstein and F-16 multisines repeat to 0.03 % and 0.14 %; a
# random or swept input differs by about 100 %.
REPEAT_TOLERANCE = 0.01
MAX_TRIED = 8  # candidate periods checked over the whole record (each a pass over it)


@dataclass(frozen=True)
class PeriodNoise:
    """The noise between periods: ``rms`` = σ̂ (the output's units), from ``periods`` periods
    of ``period`` samples (pooled over records: the sum of their periods), ``dof`` = P(M − 1)."""

    rms: float
    periods: int
    period: int
    dof: int

    @property
    def standard_error(self) -> float:
        """σ̂/√(2·dof), the standard error of σ̂ for white Gaussian noise (coloured noise has
        fewer independent samples, and a wider one)."""
        return self.rms / np.sqrt(2 * self.dof)

    def beneath(self, rms: float) -> float:
        """The part of a free-run ``rms`` over the same records that is not this noise,
        √(rms² − σ̂²); zero when rms is within two standard errors of σ̂, as far as the
        records can tell."""
        room = rms**2 - self.rms**2
        return float(np.sqrt(room)) if room > 4 * self.rms * self.standard_error else 0.0


def period_noise(x: np.ndarray, y: np.ndarray) -> PeriodNoise | None:
    """The noise between the periods of one record (module docstring); None when x does not
    repeat at least twice with a period of ``MIN_PERIOD`` samples or more.

    The period is the shortest lag at which x repeats within ``REPEAT_TOLERANCE``; samples after
    the last whole period are left out. With three periods or more the first is left out too: it
    holds the start-up transient when the record begins with the excitation.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    period = excitation_period(x)
    if period is None:
        return None
    whole = len(x) // period
    first = 1 if whole >= 3 else 0
    Y = y[first * period : whole * period].reshape(whole - first, period)
    M = Y.shape[0]
    dof = period * (M - 1)
    spread = float(np.sum((Y - Y.mean(axis=0)) ** 2))
    return PeriodNoise(float(np.sqrt(spread / dof)), M, period, dof)


def pooled_period_noise(records: Sequence[tuple[np.ndarray, np.ndarray]]) -> PeriodNoise | None:
    """The noise between periods pooled over ``records`` (σ̂² weighted by degrees of freedom):
    None unless every record is periodic, since the floor must hold for all the data it judges.
    The reported period is the first record's."""
    found = [period_noise(x, y) for x, y in records]
    if not found or any(noise is None for noise in found):
        return None
    noises = [noise for noise in found if noise is not None]
    dof = sum(noise.dof for noise in noises)
    variance = sum(noise.rms**2 * noise.dof for noise in noises) / dof
    return PeriodNoise(float(np.sqrt(variance)), sum(n.periods for n in noises), noises[0].period, dof)


def excitation_period(x: np.ndarray) -> int | None:
    """The shortest lag P ≥ ``MIN_PERIOD`` over which x repeats at least twice, or None.

    The correlation ρ(P) between x[:n−P] and x[P:] is computed for every lag at once (FFT). A
    repeat within tolerance δ has ρ ≥ 1 − 2δ² (two periods differing by 2δ RMS, each δ from
    their mean), at a local maximum of ρ; such lags, shortest first and at most ``MAX_TRIED``,
    are then checked over the whole periods. A slowly varying x has ρ near 1 at short lags, but
    falling: no maximum there.
    """
    n = len(x)
    if n < 2 * MIN_PERIOD or not np.all(np.isfinite(x)):
        return None
    centred = x - x.mean()
    if not np.any(centred):
        return None
    size = 1 << (2 * n - 1).bit_length()
    spectrum = np.fft.rfft(centred, size)
    products = np.fft.irfft(spectrum * np.conj(spectrum), size)[: n // 2 + 1]
    squares = np.concatenate(([0.0], np.cumsum(centred**2)))
    lags = np.arange(n // 2 + 1)
    head = squares[n - lags]  # Σ x[:n−P]²
    tail = squares[n] - squares[lags]  # Σ x[P:]²
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = products / np.sqrt(head * tail)
    rho = np.append(rho, -np.inf)  # the longest lag, n // 2, is a maximum if it qualifies
    inner = rho[MIN_PERIOD:-1]
    peaks = (
        (inner >= 1 - 2 * REPEAT_TOLERANCE**2)
        & (inner >= rho[MIN_PERIOD - 1 : -2])
        & (inner >= rho[MIN_PERIOD + 1 :])
    )
    for lag in (np.flatnonzero(peaks) + MIN_PERIOD)[:MAX_TRIED]:
        whole = n // lag
        X = x[: whole * lag].reshape(whole, lag)
        spread = np.sqrt(np.mean((X - X.mean(axis=0)) ** 2))
        if spread <= REPEAT_TOLERANCE * np.std(x):
            return int(lag)
    return None
