"""Validation of excitation/response pairs before any estimation touches them.

Three rules live here so that every caller states the same numbers: how long a record must be
for its residual tests (:func:`minimum_samples`), how large its values may be before the sums
of squares the estimators form overflow (:func:`magnitude_limit`), and which samples lie so far
out that they are more likely glitches than response (:func:`glitches`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
from numpy.typing import ArrayLike

from models.errors import InputError

Record = tuple[np.ndarray, np.ndarray]

# A correlation test of h lags (Ljung–Box, the cross-correlation tests) has no meaningful
# distribution on fewer than 5·h + 8 residual samples.
SAMPLES_PER_LAG = 5
EXTRA_SAMPLES = 8
# What a sum of squared products of record values (a Gram matrix, Σe², an autocovariance) may
# reach: 10¹⁰⁸ below the largest double, room for a model's coefficients, for the powers of the
# fault magnitude k in the functional coefficients, and for summing over the terms.
SUM_OF_SQUARES_LIMIT = 1e200
# A sample is a glitch beyond this many times the 99th percentile of the samples' distances
# from their median (:func:`glitches`).
GLITCH_FACTOR = 6.0
GLITCH_QUANTILE = 0.99


def minimum_samples(lags: int, longest_lag: int = 0) -> int:
    """The shortest record whose residual can be tested at ``lags`` lags after a model whose
    longest lag is ``longest_lag`` has used its first samples to start its predictions.

    With ``longest_lag`` 0 it is the shortest record worth storing: no model can do with less.
    """
    return int(longest_lag) + SAMPLES_PER_LAG * int(lags) + EXTRA_SAMPLES


def magnitude_limit(n_samples: int, degree: int = 1) -> float:
    """The largest magnitude a record's values may have for terms of ``degree`` over ``n_samples``.

    A regressor of degree d built from values of magnitude A is at most A^d, so a sum of n of
    its squares is at most n·A^(2d); that stays below :data:`SUM_OF_SQUARES_LIMIT` when
    A ≤ (limit / n)^(1/(2d)). For 2000 samples that is 2·10⁹⁸ for linear terms and 6·10³² for
    cubic ones: far above any physical record in SI units, far below the values (y·10⁶⁰,
    x·10²⁰⁰) whose statistics come out infinite or NaN.
    """
    return float((SUM_OF_SQUARES_LIMIT / max(int(n_samples), 1)) ** (1.0 / (2 * max(int(degree), 1))))


def glitches(values: np.ndarray, factor: float = GLITCH_FACTOR) -> np.ndarray:
    """Indices of the samples lying more than ``factor`` times as far from the median as the
    99th percentile of all the samples' distances from it: |v[t] − m| > factor · q, where
    m = median(v) and q = quantile₀.₉₉(|v − m|). Empty when q is 0.

    Measured signals stay within 2.2·q (Silverbox, the F-16's sweeps and multisines, the
    Wiener–Hammerstein records: 78 inputs and outputs), a Gaussian of 10⁶ samples within about
    1.9·q and a Laplacian within 3·q; one sample at ten times a record's largest lies beyond
    10·q. Least squares weighs a sample by its squared error: one at 6·q of a Gaussian (15 σ) as
    about 240 others. Glitches more than 1 % of the samples move q itself and are not found.
    """
    values = np.asarray(values, dtype=float)
    distance = np.abs(values - np.median(values))
    spread = np.quantile(distance, GLITCH_QUANTILE)
    if spread == 0:
        return np.empty(0, dtype=np.intp)
    return np.flatnonzero(distance > factor * spread)


def checked_record(
    x: ArrayLike, y: ArrayLike, min_samples: int = 1, label: str = "record", degree: int = 1
) -> Record:
    """Return (x, y) as float64 vectors, or raise :class:`InputError` saying what is wrong.

    A record must hold two one-dimensional signals of equal length, at least ``min_samples``
    long, all finite, neither signal constant (a constant carries no information about the
    dynamics and makes every regression singular), and no value beyond
    :func:`magnitude_limit` for terms of ``degree`` (the statistics would overflow).
    """
    try:
        xa = np.asarray(x, dtype=np.float64)
        ya = np.asarray(y, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{label}: signals must be numbers ({exc})") from None
    if xa.ndim != 1 or ya.ndim != 1:
        raise InputError(f"{label}: x and y must be one-dimensional, got shapes {xa.shape} and {ya.shape}")
    if xa.size != ya.size:
        raise InputError(f"{label}: x has {xa.size} samples but y has {ya.size}; they must be equal")
    if xa.size < min_samples:
        raise InputError(f"{label}: {xa.size} samples is too short; this needs at least {min_samples}")
    limit = magnitude_limit(xa.size, degree)
    for name, values in (("x", xa), ("y", ya)):
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise InputError(
                f"{label}: {name} has {bad.size} NaN or infinite value(s), first at sample {bad[0]}"
            )
        if values.size and np.ptp(values) == 0.0:
            raise InputError(f"{label}: {name} is constant; a record needs a varying signal")
        peak = float(np.max(np.abs(values))) if values.size else 0.0
        if peak > limit:
            raise InputError(
                f"{label}: {name} reaches {peak:.3g} in magnitude; with {xa.size} samples and terms of "
                f"degree {degree} the statistics overflow beyond {limit:.3g}: rescale the record "
                "(e.g. to SI units)"
            )
    return xa, ya


def checked_records(
    records: Iterable[tuple[ArrayLike, ArrayLike]], min_samples: int, degree: int = 1
) -> Sequence[Record]:
    """Validate several records for terms of ``degree``, naming the offending one by its position."""
    checked = [
        checked_record(x, y, min_samples, label=f"record {i + 1}", degree=degree)
        for i, (x, y) in enumerate(records)
    ]
    if not checked:
        raise InputError("at least one record is needed")
    return checked
