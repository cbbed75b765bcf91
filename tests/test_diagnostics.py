"""Residual autocorrelation and the Ljung–Box test against statsmodels."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal, stats
from statsmodels.stats.diagnostic import acorr_ljungbox
from statsmodels.tsa.stattools import acf

from models.diagnostics import autocorrelation, ljung_box


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
