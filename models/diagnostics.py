"""Residual diagnostics: sample autocorrelation, Ljung–Box, and the whole battery at once.

:func:`autocorrelation` and :func:`ljung_box` serve the inspection chain; :func:`residual_report`
runs Ljung–Box, the correlation tests of :mod:`models.correlation_tests` and the spectral test of
:mod:`models.spectrum` at one overall false-alarm rate.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Self

import numpy as np
from numpy.typing import ArrayLike
from scipy import special

from models.correlation_tests import (
    BillingsVoonTests,
    BillingsZhuTests,
    CorrelationTest,
    billings_voon,
    billings_zhu,
)
from models.errors import InputError
from models.series import checked_series, sidak
from models.spectrum import ResidualSpectrum, residual_spectrum


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

    @classmethod
    def of(cls, q: float, df: int, lags: int, alpha: float, **more: int) -> Self:
        """The statistic ``q`` compared with χ²_{1−α}(df); ``more``, a subclass's own fields."""
        return cls(
            q=q,
            q_critical=float(special.chdtri(df, alpha)),
            p_value=float(special.chdtrc(df, q)),
            df=df,
            lags=lags,
            **more,
        )


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
    return LjungBoxResult.of(q, df, lags, alpha)


@dataclass(frozen=True)
class HoskingResult(LjungBoxResult):
    """Hosking's multivariate portmanteau test of a vector residual's whiteness.

    Q = N²·Σ_{h=1..m} tr(Ĉ_hᵀ Ĉ_0⁻¹ Ĉ_h Ĉ_0⁻¹)/(N − h), with Ĉ_h = (1/N)·Σ_t e_t·e_{t−h}ᵀ the
    residual's lag-h autocovariance (demeaned), compared with χ²_{1−α}(K²·m − model_df) for K
    channels and m lags (Hosking 1980, "The multivariate portmanteau statistic", JASA 75).
    The cross-covariances count: a residual white on every channel whose channels lead one
    another is not white as a vector. For K = 1 it is Ljung–Box's Q scaled by N/(N + 2).
    Its fields and ``white`` are Ljung–Box's, with the number of ``channels``.
    """

    channels: int


def hosking(e: ArrayLike, lags: int = 40, alpha: float = 0.05, model_df: int = 0) -> HoskingResult:
    """Hosking's portmanteau test (:class:`HoskingResult`) of the residual ``e``, an (N, K) array
    of K channels; ``model_df`` the parameters estimated, subtracted from the degrees of freedom.
    Agrees with statsmodels' ``VARResults.test_whiteness(lags, adjusted=True)`` for a VAR's
    residual with ``model_df`` = K²·p."""
    residual = np.asarray(e, dtype=np.float64)
    if residual.ndim != 2 or residual.shape[1] < 1:
        raise InputError(f"the residual must be an (N, K) array of K channels, got shape {residual.shape}")
    n, channels = residual.shape
    df = channels**2 * lags - model_df
    if not 1 <= lags < n or df < 1:
        raise InputError(
            f"{lags} lags of {n} samples of {channels} channels with {model_df} parameters leave no "
            "degrees of freedom for the portmanteau test"
        )
    if not np.all(np.isfinite(residual)):
        raise InputError("the residual holds values that are not finite")
    centred = residual - residual.mean(axis=0)
    c0_inv = np.linalg.pinv(centred.T @ centred / n)
    q = 0.0
    for h in range(1, lags + 1):
        ch = centred[h:].T @ centred[:-h] / n
        q += float(np.trace(ch.T @ c0_inv @ ch @ c0_inv)) / (n - h)
    q *= n**2
    return HoskingResult.of(q, df, lags, alpha, channels=channels)


REPORT_TESTS = 9  # Ljung–Box, five Billings–Voon, two Billings–Zhu, the spectrum
SCALAR_CORRELATION_FIELDS = ("definition", "alpha", "statistic", "critical", "passed", "worst_lag", "outside")
SCALAR_SPECTRUM_FIELDS = ("alpha", "passed", "threshold", "dof", "segments", "peaks")


@dataclass(frozen=True, eq=False)
class ResidualReport:
    """Every residual test of one record, each at ``test_alpha`` so that the family is at ``alpha``."""

    alpha: float
    test_alpha: float
    n_samples: int
    max_lag: int
    ljung_box: LjungBoxResult
    billings_voon: BillingsVoonTests
    billings_zhu: BillingsZhuTests
    spectrum: ResidualSpectrum

    @property
    def correlation_tests(self) -> tuple[CorrelationTest, ...]:
        return self.billings_voon.tests + self.billings_zhu.tests

    @property
    def failed(self) -> tuple[str, ...]:
        """Names of the tests that reject the model, in the report's order."""
        names = ["ljung_box"] if not self.ljung_box.white else []
        names += [test.name for test in self.correlation_tests if not test.passed]
        return tuple(names + ([] if self.spectrum.passed else ["spectrum"]))

    @property
    def passed(self) -> bool:
        return not self.failed

    def to_dict(self, series: bool = True) -> dict[str, Any]:
        """JSON-serialisable figures; ``series=False`` leaves out the correlation functions and spectra."""
        tests = {}
        for test in self.correlation_tests:
            figures = test.to_dict()
            tests[test.name] = figures if series else {k: figures[k] for k in SCALAR_CORRELATION_FIELDS}
        spectrum = self.spectrum.to_dict()
        return {
            "alpha": self.alpha,
            "test_alpha": self.test_alpha,
            "n_samples": self.n_samples,
            "max_lag": self.max_lag,
            "passed": self.passed,
            "failed": list(self.failed),
            "ljung_box": {**asdict(self.ljung_box), "white": self.ljung_box.white},
            "correlation_tests": tests,
            "spectrum": spectrum if series else {k: spectrum[k] for k in SCALAR_SPECTRUM_FIELDS},
        }


def residual_report(
    u: ArrayLike,
    y: ArrayLike,
    e: ArrayLike,
    fs: float,
    max_lag: int = 40,
    alpha: float = 0.05,
    nperseg: int | None = None,
) -> ResidualReport:
    """Run every residual test on one record: u the input, y the output, e(t) = y(t) − ŷ(t).

    The tests are Ljung–Box on ``max_lag`` lags (``model_df`` = 0: no correction for the
    estimated parameters, which makes Q conservative for a fitted model), the five
    :func:`billings_voon` tests, the two :func:`billings_zhu` tests and the
    :func:`residual_spectrum` at sampling frequency ``fs`` [Hz]. ``alpha`` is the level of the
    whole report: each of the nine tests runs at 1 − (1 − α)^{1/9} (Šidák), so that a valid
    model fails ``passed`` with probability of about α or less, and a refinement loop can stop
    on it. The series must be aligned and of equal length (drop the model's start-up samples
    from all three).
    """
    u, y, e = checked_series(max_lag, alpha, u=u, y=y, e=e)
    test_alpha = sidak(alpha, REPORT_TESTS)
    return ResidualReport(
        alpha=float(alpha),
        test_alpha=test_alpha,
        n_samples=e.size,
        max_lag=int(max_lag),
        ljung_box=ljung_box(e, lags=int(max_lag), alpha=test_alpha, model_df=0),
        billings_voon=billings_voon(u, e, max_lag, test_alpha),
        billings_zhu=billings_zhu(u, y, e, max_lag, test_alpha),
        spectrum=residual_spectrum(e, fs, test_alpha, nperseg),
    )
