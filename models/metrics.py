"""Error measures for model quality (SPEC §3): RMS and normalised RMS error."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from models.errors import InputError


def rms(error: ArrayLike) -> float:
    """Root mean square √(mean(e²)), in the units of e."""
    e = np.asarray(error, dtype=np.float64)
    if e.size == 0:
        raise InputError("the RMS of an empty series is undefined")
    return float(np.sqrt(np.mean(e**2)))


def nrmse(measured: ArrayLike, predicted: ArrayLike) -> float:
    """Normalised RMS error RMS(y − ŷ)/std(y): 0 is perfect, 1 is no better than the mean.

    NaN entries of ``predicted`` (a free-run simulation that diverged) make the result inf.
    """
    y = np.asarray(measured, dtype=np.float64)
    y_hat = np.asarray(predicted, dtype=np.float64)
    if y.shape != y_hat.shape:
        raise InputError(f"measured and predicted differ in shape: {y.shape} and {y_hat.shape}")
    spread = np.std(y)
    if not spread > 0:
        raise InputError("the measured signal is constant: its NRMSE is undefined")
    if np.isnan(y_hat).any():
        return float("inf")
    return rms(y - y_hat) / float(spread)
