"""Correlation tests of a model's residual: Billings–Voon (1986) and Billings–Zhu (1994).

Each test computes a normalised correlation function over a range of lags and decides for all
its lags at once (Šidák over the lags), so that a valid model fails it with probability α.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy import special

from models.series import checked_series, sidak


@dataclass(frozen=True, eq=False)
class CorrelationTest:
    """A normalised correlation function over a lag range, and one decision for all its lags.

    ``values[i]`` is φ(τ = ``lags[i]``) as ``definition`` states it: for two series a and b,
    φ_ab(s) = Σ_t a′(t)·b′(t − s) / (N·σ_a·σ_b), a′ and b′ demeaned, σ their population standard
    deviations and the sum over the N − |s| overlapping samples (the biased estimator of
    Box & Jenkins). Under the null hypothesis φ(τ) is approximately normal with mean 0 and
    standard deviation ``sd[i]``: 1/√N when a and b are independent and one of them is i.i.d.,
    and a conditional-variance estimate for the output–residual tests (see :func:`billings_zhu`).

    **Pass/fail for many lags at once.** ``statistic`` = max_τ |φ(τ)|/sd(τ) is compared with
    ``critical`` = z_{1−α_m/2}, the Šidák quantile for the m = ``lags.size`` lags tested,
    α_m = 1 − (1 − α)^{1/m}, so a valid model fails with probability at most about α for the
    whole function, not α per lag (exact for independent lags; for jointly normal dependent ones
    Šidák's inequality keeps it at or below α). A rule allowing a binomial fraction of lags
    outside the pointwise band was rejected: it lets one large spike (an MA(1) residual's
    φ_ee(1)) pass. ``critical`` carries a first-order Cornish–Fisher correction for the excess
    kurtosis (k_a·k_b − 3)/N of a sum of N products of independent series with kurtoses k_a, k_b:
    without it the tests on squared series (φ_u²′e², k_a·k_b ≈ 225 for squared normal signals) reject
    7 % of white residuals at α = 0.05, N = 2000. ``band`` = critical·sd is the decision band
    and ``pointwise_band`` = z_{1−α/2}·sd the customary per-lag (1 − α) band for plots;
    ``outside`` counts the lags beyond the latter (information only).
    """

    name: str
    definition: str
    lags: np.ndarray
    values: np.ndarray
    sd: np.ndarray
    n_samples: int
    alpha: float
    statistic: float
    critical: float
    worst_lag: int
    outside: int

    @property
    def passed(self) -> bool:
        return self.statistic <= self.critical

    @property
    def band(self) -> np.ndarray:
        return self.critical * self.sd

    @property
    def pointwise_band(self) -> np.ndarray:
        return float(special.ndtri(1.0 - self.alpha / 2.0)) * self.sd

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable figures, the correlation function and its bands included."""
        return {
            "name": self.name,
            "definition": self.definition,
            "n_samples": self.n_samples,
            "alpha": self.alpha,
            "statistic": self.statistic,
            "critical": self.critical,
            "passed": self.passed,
            "worst_lag": self.worst_lag,
            "outside": self.outside,
            "lags": self.lags.tolist(),
            "values": self.values.tolist(),
            "band": self.band.tolist(),
            "pointwise_band": self.pointwise_band.tolist(),
        }


@dataclass(frozen=True, eq=False)
class BillingsVoonTests:
    """The five correlation tests of Billings & Voon (1986) on one residual."""

    ee: CorrelationTest
    ue: CorrelationTest
    e_eu: CorrelationTest
    u2_e: CorrelationTest
    u2_e2: CorrelationTest

    @property
    def tests(self) -> tuple[CorrelationTest, ...]:
        return (self.ee, self.ue, self.e_eu, self.u2_e, self.u2_e2)


@dataclass(frozen=True, eq=False)
class BillingsZhuTests:
    """The two output–residual correlation tests of Billings & Zhu (1994)."""

    ye_e2: CorrelationTest
    ye_u2: CorrelationTest

    @property
    def tests(self) -> tuple[CorrelationTest, ...]:
        return (self.ye_e2, self.ye_u2)


def _kurtosis(x: np.ndarray) -> float:
    """E[x⁴]/E[x²]² of a demeaned series (3 for a normal one)."""
    return float(np.mean(x**4) / np.mean(x**2) ** 2)


def _correlation_test(
    name: str,
    definition: str,
    a: np.ndarray,
    b: np.ndarray,
    lags: np.ndarray,
    alpha: float,
    shift: int = 0,
    conditional_variance: np.ndarray | None = None,
) -> CorrelationTest:
    """φ_ab(τ + ``shift``) for τ in ``lags``, and its test (see :class:`CorrelationTest`).

    ``conditional_variance[t]`` estimates E[a′(t)² | b, the past] under the null hypothesis;
    the standard deviation of φ_ab(s) is then √(Σ_t c(t)·b′(t − s)²)/(N·σ_a·σ_b) instead of 1/√N.
    """
    a = a - a.mean()
    b = b - b.mean()
    n = a.size
    scale = n * a.std() * b.std()
    rows = [slice(s, n) if s >= 0 else slice(0, n + s) for s in lags + shift]
    partners = [b[: n - s] if s >= 0 else b[-s:] for s in lags + shift]
    values = np.array([np.dot(a[r], p) for r, p in zip(rows, partners, strict=True)]) / scale
    if conditional_variance is None:
        sd = np.full(values.size, 1.0 / np.sqrt(n))
    else:
        sd = (
            np.sqrt([np.dot(conditional_variance[r], p**2) for r, p in zip(rows, partners, strict=True)])
            / scale
        )
    z = float(special.ndtri(1.0 - sidak(alpha, lags.size) / 2.0))
    excess_kurtosis = (_kurtosis(a) * _kurtosis(b) - 3.0) / n
    standardised = np.abs(values) / sd
    worst = int(np.argmax(standardised))
    return CorrelationTest(
        name=name,
        definition=definition,
        lags=lags,
        values=values,
        sd=sd,
        n_samples=n,
        alpha=float(alpha),
        statistic=float(standardised[worst]),
        critical=z + excess_kurtosis * (z**3 - 3.0 * z) / 24.0,
        worst_lag=int(lags[worst]),
        outside=int(np.sum(standardised > special.ndtri(1.0 - alpha / 2.0))),
    )


def residual_autocorrelation(e: ArrayLike, max_lag: int = 40, alpha: float = 0.05) -> CorrelationTest:
    """φ_ee(τ) = Σ_t e′(t)e′(t − τ) / Σ_t e′(t)², τ = 1 … L (the values of :func:`autocorrelation`).

    A white residual has φ_ee(τ) = δ(τ) (Box & Jenkins 1970; Billings & Voon 1986, test 1).
    Pass/fail as in :class:`CorrelationTest`; ``e`` in any unit (φ is dimensionless).
    """
    (e,) = checked_series(max_lag, alpha, e=e)
    return _correlation_test(
        "phi_ee", "corr(e(t), e(t-tau)), tau = 1..L", e, e, np.arange(1, max_lag + 1), alpha
    )


def input_cross_correlation(
    u: ArrayLike, e: ArrayLike, max_lag: int = 40, alpha: float = 0.05
) -> CorrelationTest:
    """φ_ue(τ) = Σ_t e′(t)u′(t − τ) / (N·σ_u·σ_e), τ = −L … L.

    Sign convention: τ > 0 pairs the residual with the input τ samples *earlier* (the input
    leads), so an omitted term b·u(t − d) shows at τ = +d. This is Billings & Voon's
    φ_ue(τ) = E[u(t)e(t + τ)], and ``statsmodels.tsa.stattools.ccf(e, u, adjusted=False)[τ]``
    for τ ≥ 0. A model valid in open loop has φ_ue(τ) = 0 for every τ (Billings & Voon 1986,
    test 2).
    """
    u, e = checked_series(max_lag, alpha, u=u, e=e)
    lags = np.arange(-max_lag, max_lag + 1)
    return _correlation_test("phi_ue", "corr(e(t), u(t-tau)), tau = -L..L", e, u, lags, alpha)


def billings_voon(u: ArrayLike, e: ArrayLike, max_lag: int = 40, alpha: float = 0.05) -> BillingsVoonTests:
    """The five correlation tests of Billings & Voon (1986) for a NARX(MAX) residual e and input u.

    With x′ the demeaned series, u²′(t) = u(t)² − mean(u²) and e²′(t) = e(t)² − mean(e²), a model
    is adequate when

    - φ_ee(τ) = corr(e(t), e(t − τ)) = δ(τ)             (:func:`residual_autocorrelation`)
    - φ_ue(τ) = corr(e(t), u(t − τ)) = 0 ∀τ             (:func:`input_cross_correlation`)
    - φ_e(eu)(τ) = corr(e(t), e′u′(t − 1 − τ)) = 0, τ = 0 … L − 1
    - φ_u²′e(τ) = corr(e(t), u²′(t − τ)) = 0, τ = −L … L
    - φ_u²′e²(τ) = corr(e²′(t), u²′(t − τ)) = 0, τ = −L … L

    every corr normalised as in :class:`CorrelationTest`, so that ±z/√N is the band
    (Billings, S.A., Voon, W.S.F., 1986, Correlation based model validity tests for non-linear
    models, Int. J. Control 44(1), 235–244; the product e′u′ is demeaned before it is
    correlated). τ > 0 always means the input or product *leads* the residual. The u²-based
    tests see even (e.g. quadratic) omissions; an odd one (cubic) under symmetric excitation
    leaves them near zero: see :func:`billings_zhu`. Each test has level α.
    """
    u, e = checked_series(max_lag, alpha, u=u, e=e)
    two_sided = np.arange(-max_lag, max_lag + 1)
    eu = (e - e.mean()) * (u - u.mean())
    return BillingsVoonTests(
        ee=residual_autocorrelation(e, max_lag, alpha),
        ue=input_cross_correlation(u, e, max_lag, alpha),
        e_eu=_correlation_test(
            "phi_e(eu)", "corr(e(t), e'u'(t-1-tau)), tau = 0..L-1", e, eu, np.arange(max_lag), alpha, shift=1
        ),
        u2_e=_correlation_test("phi_u2'e", "corr(e(t), u^2'(t-tau)), tau = -L..L", e, u**2, two_sided, alpha),
        u2_e2=_correlation_test(
            "phi_u2'e2", "corr(e^2'(t), u^2'(t-tau)), tau = -L..L", e**2, u**2, two_sided, alpha
        ),
    )


def billings_zhu(
    u: ArrayLike, y: ArrayLike, e: ArrayLike, max_lag: int = 40, alpha: float = 0.05
) -> BillingsZhuTests:
    """Output–residual correlation tests of Billings & Zhu (1994), which see odd nonlinearities.

    ``y`` is the measured output and ``e`` its one-step-ahead prediction error, aligned:
    e(t) = y(t) − ŷ(t). With the series α(t) = y(t)e(t), β(t) = e(t)² and u²(t), each demeaned
    (α here is Billings & Zhu's name for the series, not the test level),

    - φ_αβ(τ) = corr(α(t), β(t − τ)) = κ·δ(τ), tested at τ = −L … L, τ ≠ 0
    - φ_αu²(τ) = corr(α(t), u²′(t − τ)) = 0, tested at τ = −L … L

    (Billings, S.A., Zhu, Q.M., 1994, Nonlinear model validation using correlation tests,
    Int. J. Control 60(6), 1107–1120; sign convention and normalisation as in
    :func:`input_cross_correlation`: τ > 0 pairs α(t) with earlier β or u².) Why they work:
    an omitted odd term c·g(·) leaves e = ξ + c·r with r odd in the signals, so under symmetric
    excitation E[u²′·e] = 0 and E[u²′·e²] is only of order c², while y·e = ŷ·e + e² contains
    c·ŷ·r, even and of first order in c, which correlates with u²′ and with past e².
    φ_αβ(0) ≠ 0 by construction.

    **Band.** α and u² (or past e²) are *not* independent under the null hypothesis: ŷ depends
    on past inputs and residuals, and the usual ±z/√N band let φ_αu² reject 9–11 % of valid
    models at α = 0.05 (measured, N = 500–2000). The standard deviation of each φ(τ) is
    therefore estimated from the null conditional variance
    E[α′(t)² | past] = σ²·ŷ(t)² + 2·μ₃·ŷ(t) + E[(e² − E[ye])²], with ŷ = y − e and the moments of e
    (see :class:`CorrelationTest`). (The omni-directional tests of Zhang, Zhu & Longden (2007),
    which correlate further powers of the series, are not implemented.)
    """
    u, y, e = checked_series(max_lag, alpha, u=u, y=y, e=e)
    ye = y * e
    y_hat = y - e
    mean_ye = float(ye.mean())
    conditional = (
        np.mean(e**2) * y_hat**2 + 2.0 * np.mean(e**3) * y_hat + float(np.mean((e**2 - mean_ye) ** 2))
    )
    lags = np.arange(-max_lag, max_lag + 1)
    return BillingsZhuTests(
        ye_e2=_correlation_test(
            "phi_(ye)'(e2)'",
            "corr((ye)'(t), e^2'(t-tau)), tau = -L..L, tau != 0",
            ye,
            e**2,
            lags[lags != 0],
            alpha,
            conditional_variance=conditional,
        ),
        ye_u2=_correlation_test(
            "phi_(ye)'(u2)'",
            "corr((ye)'(t), u^2'(t-tau)), tau = -L..L",
            ye,
            u**2,
            lags,
            alpha,
            conditional_variance=conditional,
        ),
    )
