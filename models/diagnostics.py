"""Residual diagnostics: sample autocorrelation and the Ljung–Box whiteness test."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import special


def autocorrelation(e: np.ndarray, max_lag: int) -> np.ndarray:
    """Sample autocorrelation ρ̂_0 … ρ̂_h of a demeaned series (biased estimator, as in Box–Jenkins)."""
    centred = e - e.mean()
    n_fft = 1 << int(np.ceil(np.log2(2 * len(centred) - 1)))
    spectrum = np.fft.rfft(centred, n_fft)
    autocovariance = np.fft.irfft(spectrum.real**2 + spectrum.imag**2, n_fft)[: max_lag + 1]
    return autocovariance / autocovariance[0]


@dataclass(frozen=True)
class LjungBoxResult:
    """Q = N(N+2)·Σ_{i=1..h} ρ̂_i²/(N − i), compared with χ²_{1−α}(h − model_df)."""

    q: float
    q_critical: float
    p_value: float
    df: int
    lags: int

    @property
    def white(self) -> bool:
        return self.q < self.q_critical


def ljung_box(e: np.ndarray, lags: int = 40, alpha: float = 0.05, model_df: int = 1) -> LjungBoxResult:
    """Ljung–Box portmanteau test of residual whiteness (SPEC §5, step 4).

    ``model_df`` is subtracted from the degrees of freedom; the paper uses h − 1 for the one
    estimated magnitude k. Agrees with ``statsmodels.stats.diagnostic.acorr_ljungbox(e,
    lags=[h], model_df=model_df)``.
    """
    n = len(e)
    rho = autocorrelation(np.asarray(e, dtype=np.float64), lags)[1:]
    q = float(n * (n + 2) * np.sum(rho**2 / (n - np.arange(1, lags + 1))))
    df = lags - model_df
    return LjungBoxResult(
        q=q,
        q_critical=float(special.chdtri(df, alpha)),
        p_value=float(special.chdtrc(df, q)),
        df=df,
        lags=lags,
    )
