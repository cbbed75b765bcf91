"""Validated residual series and the multiple-test levels the diagnostics share."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from models.errors import InputError
from models.signals import EXTRA_SAMPLES, SAMPLES_PER_LAG, minimum_samples


def _series(values: ArrayLike, name: str) -> np.ndarray:
    try:
        series = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} must be numbers ({exc})") from None
    if series.ndim != 1:
        raise InputError(f"{name} must be one-dimensional, got shape {series.shape}")
    bad = np.flatnonzero(~np.isfinite(series))
    if bad.size:
        raise InputError(f"{name} has {bad.size} NaN or infinite value(s), first at sample {bad[0]}")
    if series.size and np.ptp(series) == 0.0:
        raise InputError(f"{name} is constant; its correlations are undefined")
    return series


def checked_series(max_lag: int, alpha: float, **named: ArrayLike) -> list[np.ndarray]:
    """Validate α, equal-length finite series and the lag range (N ≥ 5·max_lag + 8)."""
    if not 0.0 < alpha < 0.5:
        raise InputError(f"alpha must lie in (0, 0.5), got {alpha}")
    series = [_series(values, name) for name, values in named.items()]
    names = list(named)
    for name, values in zip(names[1:], series[1:], strict=True):
        if values.size != series[0].size:
            raise InputError(
                f"{names[0]} has {series[0].size} samples but {name} has {values.size}; they must be equal"
            )
    if isinstance(max_lag, bool) or not isinstance(max_lag, int | np.integer) or max_lag < 1:
        raise InputError(f"max_lag must be a whole number of at least 1, got {max_lag!r}")
    n = series[0].size
    needed = minimum_samples(max_lag)
    if n < needed:
        raise InputError(
            f"{n} samples is too short for max_lag = {max_lag}: the tests need at least "
            f"{SAMPLES_PER_LAG}·max_lag + {EXTRA_SAMPLES} = {needed}; use max_lag ≤ "
            f"{max(0, (n - EXTRA_SAMPLES) // SAMPLES_PER_LAG)} or a longer record"
        )
    return series


def sidak(alpha: float, m: int) -> float:
    """Per-test level 1 − (1 − α)^{1/m} that keeps the level of m independent tests at α."""
    return float(-np.expm1(np.log1p(-alpha) / m))
