"""Residual diagnostics: Ljung–Box against statsmodels; the correlation tests against direct sums,
statsmodels and their false-alarm rates; the residual spectrum against theory; the report."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from scipy import signal, stats

from models.correlation_tests import (
    CorrelationTest,
    billings_voon,
    billings_zhu,
    input_cross_correlation,
    residual_autocorrelation,
)
from models.diagnostics import autocorrelation, hosking, ljung_box, residual_report
from models.errors import InputError
from models.spectrum import residual_spectrum, welch_dof

# statsmodels, the independent reference of a few tests, is imported in them: every pytest-xdist
# process imports every test module at collection, and statsmodels brings pandas and patsy.


def white(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=n) + 3.0  # a mean, to check demeaning


def coloured(n: int, seed: int) -> np.ndarray:
    """AR(1) with coefficient 0.3 plus an MA(2) part: clearly not white."""
    e = np.random.default_rng(seed).normal(size=n)
    return signal.lfilter([1.0, 0.4, -0.2], [1.0, -0.3], e)


SERIES = {
    "white-2000": white(2000, 1),
    "white-257": white(257, 2),
    "coloured-2000": coloured(2000, 3),
    "coloured-500": coloured(500, 4),
}


@pytest.mark.parametrize("name", SERIES)
@pytest.mark.parametrize("h", [2, 10, 40])
def test_autocorrelation_matches_statsmodels_acf(name: str, h: int) -> None:
    from statsmodels.tsa.stattools import acf

    e = SERIES[name]
    np.testing.assert_allclose(autocorrelation(e, h), acf(e, nlags=h, fft=False), rtol=1e-10, atol=1e-13)


def test_autocorrelation_by_definition() -> None:
    e = SERIES["coloured-500"]
    c = e - e.mean()
    rho = np.array([np.sum(c[i:] * c[: len(c) - i]) for i in range(6)]) / np.sum(c * c)
    np.testing.assert_allclose(autocorrelation(e, 5), rho, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("name", SERIES)
@pytest.mark.parametrize("h", [5, 20, 40])
def test_ljung_box_matches_statsmodels(name: str, h: int) -> None:
    from statsmodels.stats.diagnostic import acorr_ljungbox

    e = SERIES[name]
    result = ljung_box(e, lags=h)
    reference = acorr_ljungbox(e, lags=[h], model_df=1)
    assert result.q == pytest.approx(float(reference["lb_stat"].iloc[0]), rel=1e-10)
    assert result.p_value == pytest.approx(float(reference["lb_pvalue"].iloc[0]), rel=1e-8, abs=1e-300)
    assert result.df == h - 1
    assert result.lags == h
    assert result.q_critical == pytest.approx(stats.chi2.ppf(0.95, h - 1), rel=1e-10)
    assert result.white == (result.q < result.q_critical)


def test_ljung_box_model_df_and_alpha() -> None:
    from statsmodels.stats.diagnostic import acorr_ljungbox

    e = SERIES["coloured-500"]
    result = ljung_box(e, lags=12, alpha=0.01, model_df=3)
    reference = acorr_ljungbox(e, lags=[12], model_df=3)
    assert result.df == 9
    assert result.p_value == pytest.approx(float(reference["lb_pvalue"].iloc[0]), rel=1e-8, abs=1e-300)
    assert result.q_critical == pytest.approx(stats.chi2.ppf(0.99, 9), rel=1e-10)


def test_ljung_box_decides_white_and_coloured() -> None:
    """The coloured series has ρ1 ≈ 0.6: Q is in the hundreds at N = 2000, p-value ≈ 0."""
    assert not ljung_box(SERIES["coloured-2000"], lags=40).white
    assert ljung_box(SERIES["coloured-2000"], lags=40).p_value < 1e-30


def test_ljung_box_size_on_white_noise() -> None:
    """On white noise Q ~ χ²(h) (model_df = 0): over 400 independent series the rejection
    rate at α = 0.05 is Binomial(400, 0.05): mean 20, sd 4.4; 4 sd either side is allowed.
    The p-values are uniform: Kolmogorov–Smirnov at the 0.001 level."""
    rng = np.random.default_rng(8)
    p_values = np.array([ljung_box(rng.normal(size=1000), lags=20, model_df=0).p_value for _ in range(400)])
    rejections = int(np.sum(p_values < 0.05))
    assert 20 - 4 * 4.4 < rejections < 20 + 4 * 4.4
    assert stats.kstest(p_values, "uniform").pvalue > 0.001


# --- Correlation tests (Billings–Voon, Billings–Zhu), the residual spectrum and the report -------------

ALPHA = 0.05


def binomial_ceiling(repetitions: int, rate: float) -> float:
    """Rejections a test of size ≤ rate exceeds with probability 0.001."""
    return float(stats.binom.ppf(0.999, repetitions, rate))


def null_record(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, y, e) of a valid model: y(t) = 0.7·y(t−1) + u(t−1) + e(t), e white and independent of u."""
    u = rng.normal(size=n)
    e = rng.normal(size=n)
    y = signal.lfilter([0.0, 1.0], [1.0, -0.7], u) + signal.lfilter([1.0], [1.0, -0.7], e)
    return u, y, e


def direct_corr(a: np.ndarray, b: np.ndarray, s: int) -> float:
    """Σ_t a′(t)·b′(t − s) / (N·σ_a·σ_b), summed term by term."""
    a = a - a.mean()
    b = b - b.mean()
    n = len(a)
    total = sum(a[t] * b[t - s] for t in range(n) if 0 <= t - s < n)
    return total / (n * np.sqrt(np.mean(a**2) * np.mean(b**2)))


def value_at(test: CorrelationTest, lag: int) -> float:
    return float(test.values[np.flatnonzero(test.lags == lag)[0]])


@pytest.fixture(scope="module")
def small_record() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Non-Gaussian, non-zero-mean signals with some structure, so that every φ is non-trivial."""
    rng = np.random.default_rng(21)
    u = rng.uniform(-1.0, 2.0, size=300)
    e = rng.standard_t(5, size=300) + 0.3 * np.roll(u, 2) ** 2 + 0.5
    y = signal.lfilter([0.0, 1.0], [1.0, -0.5], u) + e
    return u, y, e


def test_residual_autocorrelation_is_autocorrelation(small_record) -> None:
    _, _, e = small_record
    test = residual_autocorrelation(e, 12)
    np.testing.assert_array_equal(test.lags, np.arange(1, 13))
    np.testing.assert_allclose(test.values, autocorrelation(e, 12)[1:], rtol=1e-12, atol=1e-15)


def test_correlations_by_direct_sums(small_record) -> None:
    """Every φ at a few lags, from the papers' definitions summed term by term."""
    u, y, e = small_record
    bv = billings_voon(u, e, 10)
    bz = billings_zhu(u, y, e, 10)
    eu = (e - e.mean()) * (u - u.mean())
    for lag in (-7, -1, 0, 1, 3, 10):
        if lag >= 1:
            assert value_at(bv.ee, lag) == pytest.approx(direct_corr(e, e, lag), rel=1e-10)
        if 0 <= lag <= 9:  # φ_e(eu)(τ) = corr(e(t), e′u′(t − 1 − τ))
            assert value_at(bv.e_eu, lag) == pytest.approx(direct_corr(e, eu, lag + 1), rel=1e-10)
        assert value_at(bv.ue, lag) == pytest.approx(direct_corr(e, u, lag), rel=1e-10)
        assert value_at(bv.u2_e, lag) == pytest.approx(direct_corr(e, u**2, lag), rel=1e-10)
        assert value_at(bv.u2_e2, lag) == pytest.approx(direct_corr(e**2, u**2, lag), rel=1e-10)
        assert value_at(bz.ye_u2, lag) == pytest.approx(direct_corr(y * e, u**2, lag), rel=1e-10)
        if lag != 0:
            assert value_at(bz.ye_e2, lag) == pytest.approx(direct_corr(y * e, e**2, lag), rel=1e-10)
    assert 0 not in bz.ye_e2.lags  # φ_αβ(0) ≠ 0 by construction
    np.testing.assert_array_equal(bv.e_eu.lags, np.arange(10))
    np.testing.assert_array_equal(bz.ye_u2.lags, np.arange(-10, 11))


def test_input_cross_correlation_sign_convention_against_statsmodels(small_record) -> None:
    """φ_ue(τ) = corr(e(t), u(t − τ)): ccf(e, u)[τ] for τ ≥ 0 and ccf(u, e)[−τ] for τ ≤ 0."""
    from statsmodels.tsa.stattools import ccf

    u, _, e = small_record
    test = input_cross_correlation(u, e, 15)
    np.testing.assert_allclose(test.values[15:], ccf(e, u, adjusted=False, fft=False)[:16], rtol=1e-10)
    np.testing.assert_allclose(test.values[15::-1], ccf(u, e, adjusted=False, fft=False)[:16], rtol=1e-10)
    full = np.correlate(e - e.mean(), u - u.mean(), mode="full") / (len(e) * e.std() * u.std())
    np.testing.assert_allclose(test.values, full[len(e) - 1 - 15 : len(e) + 15], rtol=1e-10)


def test_output_residual_band_is_the_conditional_variance_formula(small_record) -> None:
    """sd(τ) = √(Σ_t c(t)·b′(t − τ)²)/(N·σ_α·σ_b), c(t) = σ²ŷ(t)² + 2μ₃ŷ(t) + E[(e² − E[ye])²]."""
    u, y, e = small_record
    test = billings_zhu(u, y, e, 5).ye_u2
    y_hat, ye, n = y - e, y * e, len(e)
    c = np.mean(e**2) * y_hat**2 + 2 * np.mean(e**3) * y_hat + np.mean((e**2 - ye.mean()) ** 2)
    b = u**2 - np.mean(u**2)
    for lag in (-5, 0, 2):
        s = sum(c[t] * b[t - lag] ** 2 for t in range(n) if 0 <= t - lag < n)
        expected = np.sqrt(s) / (n * ye.std() * b.std())
        assert test.sd[np.flatnonzero(test.lags == lag)[0]] == pytest.approx(expected, rel=1e-10)


def test_band_and_decision(small_record) -> None:
    """critical = Šidák z for the m lags plus the Cornish–Fisher term (κ/24)(z³ − 3z),
    κ = (k_a·k_b − 3)/N; pass ⇔ every |φ(τ)| ≤ critical·sd(τ)."""
    u, _, e = small_record
    n = len(e)
    eu = (e - e.mean()) * (u - u.mean())
    pairs = {
        "phi_ee": (e, e),
        "phi_ue": (e, u),
        "phi_e(eu)": (e, eu),
        "phi_u2'e": (e, u**2),
        "phi_u2'e2": (e**2, u**2),
    }
    for test in billings_voon(u, e, 10, alpha=0.1).tests:
        a, b = pairs[test.name]
        z = stats.norm.isf((1 - 0.9 ** (1 / test.lags.size)) / 2)
        kappa = (stats.kurtosis(a, fisher=False) * stats.kurtosis(b, fisher=False) - 3) / n
        assert test.critical == pytest.approx(z + kappa / 24 * (z**3 - 3 * z), rel=1e-10), test.name
        np.testing.assert_allclose(test.sd, 1 / np.sqrt(n))
        np.testing.assert_allclose(test.band, test.critical * test.sd)
        assert test.passed == bool(np.all(np.abs(test.values) <= test.band))
        assert test.statistic == pytest.approx(np.max(np.abs(test.values)) * np.sqrt(n))
        assert abs(value_at(test, test.worst_lag)) * np.sqrt(n) == pytest.approx(test.statistic)
        assert test.outside == int(np.sum(np.abs(test.values) > test.pointwise_band))
    assert residual_autocorrelation(e, 10).pointwise_band == pytest.approx(np.full(10, 1.959964 / np.sqrt(n)))


def test_white_residual_false_alarm_rates() -> None:
    """Valid model, white residual: each test rejects at most ≈α of 400 records (Šidák over its
    lags), and its per-lag rejection rate at the pointwise band is α (the band's scale is right)."""
    rng = np.random.default_rng(31)
    repetitions, n, lags = 400, 1000, 20
    rejections: dict[str, int] = {}
    pointwise: dict[str, float] = {}
    for _ in range(repetitions):
        u, y, e = null_record(rng, n)
        for test in billings_voon(u, e, lags).tests + billings_zhu(u, y, e, lags).tests:
            rejections[test.name] = rejections.get(test.name, 0) + (not test.passed)
            pointwise[test.name] = pointwise.get(test.name, 0.0) + test.outside / test.lags.size / repetitions
    assert len(rejections) == 7
    for name, count in rejections.items():
        assert count <= binomial_ceiling(repetitions, ALPHA), name
    for name, rate in pointwise.items():
        assert 0.04 < rate < 0.06, name


def test_report_false_alarm_rate_is_alpha_for_the_whole_family() -> None:
    rng = np.random.default_rng(32)
    repetitions = 300
    failures = 0
    for _ in range(repetitions):
        u, y, e = null_record(rng, 1000)
        report = residual_report(u, y, e, fs=1500.0, max_lag=20)
        failures += not report.passed
    assert report.test_alpha == pytest.approx(1 - 0.95 ** (1 / 9))
    assert failures <= binomial_ceiling(repetitions, ALPHA)


def test_ma1_residual_fails_autocorrelation_and_ljung_box() -> None:
    xi = np.random.default_rng(41).normal(size=1001)
    e = xi[1:] + 0.3 * xi[:-1]
    test = residual_autocorrelation(e, 20)
    assert not test.passed
    assert test.worst_lag == 1
    assert value_at(test, 1) == pytest.approx(0.3 / 1.09, abs=0.1)
    assert not ljung_box(e, lags=20).white


def test_lagged_input_in_residual_fails_cross_correlation_at_its_lag() -> None:
    rng = np.random.default_rng(42)
    u = rng.normal(size=1006)
    xi = rng.normal(size=1000)
    lagged = input_cross_correlation(u[3:1003], xi + 0.3 * u[:1000], 20)  # e(t) ∋ u(t − 3)
    leading = input_cross_correlation(u[:1000], xi + 0.3 * u[3:1003], 20)  # e(t) ∋ u(t + 3)
    assert not lagged.passed and lagged.worst_lag == 3
    assert not leading.passed and leading.worst_lag == -3
    assert input_cross_correlation(u[3:1003], xi, 20).passed


def test_omitted_quadratic_input_term_fails_u2_test_not_linear_ones() -> None:
    """y(t) = 0.5·y(t−1) + u(t−1) + 0.2·u(t−1)² + ξ(t), fitted without the square: φ_u²′e fails at
    τ = 1 while φ_ue, blind to even terms under a symmetric input, passes."""
    rng = np.random.default_rng(43)
    n = 2000
    u = rng.normal(size=n)
    y = signal.lfilter([0.0, 1.0], [1.0, -0.5], u + 0.2 * u**2) + signal.lfilter(
        [1.0], [1.0, -0.5], 0.3 * rng.normal(size=n)
    )
    X = np.column_stack([y[:-1], u[:-1], np.ones(n - 1)])
    e = y[1:] - X @ np.linalg.lstsq(X, y[1:], rcond=None)[0]
    bv = billings_voon(u[1:], e, 20)
    assert not bv.u2_e.passed and bv.u2_e.worst_lag == 1
    assert bv.ue.passed


def cubic_record(seed: int, c: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """y(t) = 1.2·y(t−1) − 0.5·y(t−2) + u(t−1) + c·y(t−1)³ + ξ(t), u ~ N(0, 0.5²), ξ ~ N(0, 0.1²)."""
    rng = np.random.default_rng(seed)
    u = 0.5 * rng.normal(size=n + 100)
    xi = 0.1 * rng.normal(size=n + 100)
    y = np.zeros(n + 100)
    for t in range(2, n + 100):
        y[t] = 1.2 * y[t - 1] - 0.5 * y[t - 2] + u[t - 1] + c * y[t - 1] ** 3 + xi[t]
    return u[100:], y[100:]


def test_omitted_cubic_term_escapes_u2_tests_but_not_output_residual_test() -> None:
    """The key case: an odd term missed under symmetric excitation.

    Fitted without c·y(t−1)³ (c = −0.003, 1 % of the residual variance), the residual is odd in
    the signals: φ_u²′e ≡ 0 by symmetry and φ_u²′e² ∝ c² stay within their bands, while
    φ_(ye)′(u²)′ ∝ c fails. Fitted with the cubic term, the same test passes. Over five records
    the test fails on every one without the term; the u² tests without it, and the test with
    it, pass on at least four (each has size ≈ α, so one record's failure would prove nothing).
    """
    n, lags = 40_000, 10
    false_alarms = {"phi_u2'e": 0, "phi_u2'e2": 0, "complete model": 0}
    for seed in range(5):
        u, y = cubic_record(seed, -0.003, n)
        X = np.column_stack([y[1:-1], y[:-2], u[1:-1]])
        e = y[2:] - X @ np.linalg.lstsq(X, y[2:], rcond=None)[0]
        assert np.var(e) < 1.02 * 0.1**2
        assert not billings_zhu(u[2:], y[2:], e, lags).ye_u2.passed, seed
        bv = billings_voon(u[2:], e, lags)
        for test in (bv.u2_e, bv.u2_e2):
            false_alarms[test.name] += not test.passed
        X = np.column_stack([X, y[1:-1] ** 3])
        e = y[2:] - X @ np.linalg.lstsq(X, y[2:], rcond=None)[0]
        false_alarms["complete model"] += not billings_zhu(u[2:], y[2:], e, lags).ye_u2.passed
    assert max(false_alarms.values()) <= 1, false_alarms


def test_welch_dof() -> None:
    """2K for non-overlapping rectangular segments; Hann at 50 % overlaps by ρ = 1/6 (Harris 1978)."""
    assert welch_dof(np.ones(64), 64, 10) == pytest.approx(20.0)
    k = 14
    assert welch_dof(signal.get_window("hann", 256), 128, k) == pytest.approx(
        2 * k / (1 + 2 * (1 - 1 / k) / 36), rel=1e-12
    )


def test_spectrum_of_white_noise_matches_theory() -> None:
    """Over 200 records of white noise (σ = 2): the PSD level is 2σ²/fs, the background estimates
    it, and the spread of the Welch estimates is that of χ²_ν/ν."""
    rng = np.random.default_rng(51)
    fs, sigma = 1500.0, 2.0
    spectra = [residual_spectrum(sigma * rng.normal(size=2000), fs) for _ in range(200)]
    psd = np.array([s.psd[1:-1] for s in spectra])
    background = np.array([s.background[1:-1] for s in spectra])
    level = 2 * sigma**2 / fs
    assert psd.mean() == pytest.approx(level, rel=0.02)
    assert background.mean() == pytest.approx(level, rel=0.02)
    dof = spectra[0].dof
    assert spectra[0].segments == 14
    assert 2 * psd.mean() ** 2 / psd.var() == pytest.approx(dof, rel=0.05)


def test_spectrum_false_alarm_rate() -> None:
    rng = np.random.default_rng(52)
    repetitions = 400
    peaks = sum(not residual_spectrum(rng.normal(size=1000), 1500.0).passed for _ in range(repetitions))
    assert peaks <= binomial_ceiling(repetitions, ALPHA)


@pytest.mark.parametrize("seed", range(5))
def test_spectrum_finds_a_weak_sinusoid(seed: int) -> None:
    """A sinusoid of amplitude 0.3 in unit white noise (−13.5 dB) is a peak within one bin of it."""
    rng = np.random.default_rng(60 + seed)
    fs, n = 1500.0, 2000
    f0 = rng.uniform(30.0, 720.0)
    t = np.arange(n) / fs
    spectrum = residual_spectrum(
        rng.normal(size=n) + 0.3 * np.sin(2 * np.pi * f0 * t + rng.uniform(0, 6)), fs
    )
    bin_width = fs / 256
    assert not spectrum.passed
    nearest = min(spectrum.peaks, key=lambda peak: abs(peak.frequency - f0))
    assert abs(nearest.frequency - f0) <= bin_width
    assert nearest.ratio > spectrum.threshold
    assert nearest.ratio == max(peak.ratio for peak in spectrum.peaks)


def test_report_collects_every_test_and_serialises() -> None:
    rng = np.random.default_rng(70)
    u, y, e = null_record(rng, 2000)
    e = e + 0.5 * np.sin(2 * np.pi * 100.0 * np.arange(2000) / 1500.0)
    report = residual_report(u, y, e, fs=1500.0, max_lag=20, alpha=0.05)
    assert len(report.correlation_tests) == 7
    assert all(test.alpha == report.test_alpha for test in report.correlation_tests)
    assert report.spectrum.alpha == report.test_alpha
    assert "spectrum" in report.failed and not report.passed
    full = json.loads(json.dumps(report.to_dict()))
    brief = json.loads(json.dumps(report.to_dict(series=False)))
    assert full["failed"] == brief["failed"] == list(report.failed)
    assert set(full["correlation_tests"]) == {test.name for test in report.correlation_tests}
    assert len(full["correlation_tests"]["phi_ue"]["values"]) == 41
    assert "values" not in brief["correlation_tests"]["phi_ue"]
    assert "psd" not in brief["spectrum"]
    assert brief["spectrum"]["peaks"][0]["frequency"] == pytest.approx(100.0, abs=1500.0 / 256)
    assert brief["ljung_box"]["q"] == pytest.approx(ljung_box(e, 20, report.test_alpha, model_df=0).q)


GOOD = np.random.default_rng(80).normal(size=(3, 200))


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: billings_voon(GOOD[0], GOOD[1][:150], 10), "u has 200 samples but e has 150"),
        (lambda: billings_zhu(GOOD[0], GOOD[1][:-1], GOOD[2], 10), "u has 200 samples but y has 199"),
        (lambda: residual_autocorrelation(np.where(np.arange(200) == 7, np.nan, GOOD[0]), 10), "NaN or inf"),
        (
            lambda: input_cross_correlation(np.where(np.arange(200) == 9, np.inf, GOOD[0]), GOOD[1]),
            "at sample 9",
        ),
        (lambda: residual_autocorrelation(GOOD[0], 200), "too short for max_lag = 200"),
        (lambda: residual_autocorrelation(GOOD[0], 39), "use max_lag ≤ 38"),
        (lambda: residual_autocorrelation(GOOD[0][:12], 1), "12 samples is too short"),
        (lambda: residual_autocorrelation(GOOD[0], 0), "max_lag must be a whole number"),
        (lambda: residual_autocorrelation(GOOD[0], 2.5), "max_lag must be a whole number"),
        (lambda: residual_autocorrelation(GOOD[0], 10, alpha=0.7), "alpha must lie in"),
        (lambda: residual_autocorrelation(np.ones(200), 10), "e is constant"),
        (lambda: residual_autocorrelation(GOOD[:2], 10), "one-dimensional"),
        (lambda: residual_autocorrelation(["a"] * 200, 10), "must be numbers"),
        (lambda: residual_spectrum(GOOD[0][:60], 1500.0), "60 samples is too short for a residual spectrum"),
        (lambda: residual_spectrum(GOOD[0], 1500.0, nperseg=128), "at least 2·nperseg = 256"),
        (lambda: residual_spectrum(GOOD[0], 0.0), "fs must be a positive"),
        (lambda: residual_spectrum(GOOD[0], float("nan")), "fs must be a positive"),
        (lambda: residual_spectrum(GOOD[0], 1500.0, smoothing_bins=4), "smoothing_bins must be odd"),
        (lambda: residual_report(GOOD[0], GOOD[1], GOOD[2][:100], 1500.0, 10), "but e has 100"),
    ],
)
def test_bad_input_is_refused_with_a_clear_message(call, message: str) -> None:
    with pytest.raises(InputError, match=re.escape(message)):
        call()


def _var1(n: int, coupling: float, seed: int) -> np.ndarray:
    """A two-channel VAR(1) whose channels are each nearly white but lead one another."""
    rng = np.random.default_rng(seed)
    a = np.array([[0.0, coupling], [0.0, 0.0]])  # channel 1 follows channel 2 one sample late
    z = np.zeros((n, 2))
    shocks = rng.standard_normal((n, 2))
    for t in range(1, n):
        z[t] = a @ z[t - 1] + shocks[t]
    return z


def test_hosking_agrees_with_statsmodels_whiteness_test_of_a_var_residual():
    from statsmodels.tsa.api import VAR

    fitted = VAR(_var1(3000, 0.6, seed=3)).fit(2, trend="c")
    expected = fitted.test_whiteness(nlags=12, adjusted=True)
    result = hosking(fitted.resid, lags=12, model_df=2**2 * 2)
    assert result.q == pytest.approx(expected.test_statistic, rel=1e-12)
    assert result.df == expected.df and result.p_value == pytest.approx(expected.pvalue, rel=1e-9)


def test_hosking_of_one_channel_is_ljung_box_scaled_by_n_over_n_plus_2():
    e = np.random.default_rng(4).standard_normal(2000)
    assert hosking(e[:, None], lags=20).q == pytest.approx(
        ljung_box(e, 20, model_df=0).q * 2000 / 2002, rel=1e-12
    )


def test_hosking_sees_channels_that_lead_one_another_where_per_channel_tests_do_not():
    z = _var1(4000, 0.5, seed=5)
    # Each channel alone is white (channel 1 is a sum of two independent white series)...
    assert all(ljung_box(z[:, i], 20, model_df=0).white for i in range(2))
    # ...but as a vector it is not: channel 1 at t is channel 2 at t − 1, halved.
    assert not hosking(z, lags=20).white


def test_hosking_rejects_white_vectors_at_its_level():
    """Over 400 independent three-channel white residuals the rejections stay within the 99 %
    binomial range of α = 0.05."""
    rng = np.random.default_rng(6)
    rejected = sum(not hosking(rng.standard_normal((1000, 3)), lags=10).white for _ in range(400))
    low, high = stats.binom.ppf([0.005, 0.995], 400, 0.05)
    assert low <= rejected <= high, rejected


@pytest.mark.parametrize(
    ("shape", "lags", "model_df", "message"),
    [
        ((100,), 5, 0, r"\(N, K\) array"),
        ((100, 2), 100, 0, "no degrees of freedom"),
        ((100, 2), 2, 8, "no degrees"),
    ],
)
def test_hosking_refuses_what_it_cannot_test(shape, lags, model_df, message):
    with pytest.raises(InputError, match=message):
        hosking(np.ones(shape), lags=lags, model_df=model_df)
