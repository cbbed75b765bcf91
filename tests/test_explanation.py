"""What each part of a refined model carries: contributions, shares, coefficients and their errors."""

from __future__ import annotations

import numpy as np
import pytest

from models.explanation import explain
from models.narx import NARX, fit_narx
from models.scoring import EffectScore
from models.terms import parse_terms

N = 3000
A, B, C = 0.8, 0.5, -0.05
TERMS = ("y[t-1]", "x[t-1]", "y[t-1]^3")


def effect(name: str, terms: tuple[str, ...], noise_lags: int = 0) -> EffectScore:
    return EffectScore(name, name, 0.5, -10.0, terms, (), (), noise_lags)


CUBIC = effect("cubic_stiffness", ("y[t-1]^3",))


def record(c: float, seed: int = 0, noise: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """y[t] = A·y[t-1] + B·x[t-1] + c·y[t-1]³ (+ an equation error of std ``noise``), white x."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=N)
    e = noise * rng.normal(size=N)
    y = np.zeros(N)
    for t in range(1, N):
        y[t] = A * y[t - 1] + B * x[t - 1] + c * y[t - 1] ** 3 + e[t]
    return x, y


def exact(c: float) -> NARX:
    return NARX(parse_terms(TERMS), np.array([A, B, c]), np.zeros((3, 3)))


def test_an_effects_contribution_is_its_terms_times_their_coefficients_along_the_free_run():
    x, y = record(C, noise=0.3)
    model = exact(C)
    explained = explain(model, [CUBIC], x, y, initial=5)
    # The free run computed here, independently of the model's compiled one.
    run = y.copy()
    for t in range(5, N):
        run[t] = A * run[t - 1] + B * x[t - 1] + C * run[t - 1] ** 3
    (cubic,) = explained.effects
    assert explained.along == "free run"
    assert explained.first == 5
    assert cubic.terms == ("y[t-1]^3",) and cubic.coefficients == (C,)
    np.testing.assert_allclose(cubic.series, C * run[4:-1] ** 3, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(explained.declared.series, A * run[4:-1] + B * x[4:-1], rtol=1e-12, atol=1e-15)
    measured = np.sqrt(np.mean(y[5:] ** 2))
    assert explained.output_rms == pytest.approx(measured)
    assert cubic.share == pytest.approx(np.sqrt(np.mean((C * run[4:-1] ** 3) ** 2)) / measured)
    assert explained.declared.terms == ("y[t-1]", "x[t-1]")
    # Removed, the free run is the linear part's, computed here.
    linear = y.copy()
    for t in range(5, N):
        linear[t] = A * linear[t - 1] + B * x[t - 1]
    assert cubic.removal == pytest.approx(np.sqrt(np.mean((linear[5:] - run[5:]) ** 2)) / measured)
    # The steps add up: through the pole at A each step's term is summed over a few samples.
    assert cubic.removal > 2 * cubic.share
    # A theoretical model has no covariance: no standard errors to report.
    assert cubic.standard_errors is None


def test_a_fitted_model_reports_its_standard_errors_and_an_absent_effect_carries_nothing():
    x, y = record(C, seed=1, noise=0.05)
    with_cubic = fit_narx([(x, y)], TERMS)
    present = explain(with_cubic, [CUBIC], x, y).effects[0]
    assert present.standard_errors == pytest.approx(tuple(with_cubic.standard_errors()[[2]]))
    assert present.standard_errors[0] > 0
    # The cubic term of the record that has it carries a visible share; fitted to a record
    # without it, its coefficient is noise, within its standard errors of zero, and its share a
    # small part of the other's.
    x, y = record(0.0, seed=1, noise=0.05)
    without = explain(fit_narx([(x, y)], TERMS), [CUBIC], x, y)
    (absent,) = without.effects
    assert present.share > 0.05
    assert abs(absent.coefficients[0]) < 3 * absent.standard_errors[0]
    assert absent.share < 0.05 * present.share
    assert without.declared.share == pytest.approx(1.0, abs=0.05)
    assert without.to_dict()["declared"]["share"] == without.declared.share


def test_a_diverging_model_is_explained_along_the_measured_outputs():
    x, y = record(C, seed=2)
    unstable = NARX(parse_terms(TERMS), np.array([1.5, B, -C]), np.zeros((3, 3)))
    explained = explain(unstable, [CUBIC], x, y)
    assert not np.all(np.isfinite(unstable.simulate(x, y)))
    assert explained.along == "one-step"
    np.testing.assert_allclose(explained.effects[0].series, -C * y[:-1] ** 3)


def test_an_effect_without_which_the_free_run_diverges_says_so():
    # A linear part that grows on its own (a = 1.02), held by a stiffening spring.
    x, y = record(C, seed=5)
    held = NARX(parse_terms(TERMS), np.array([1.02, B, C]), np.zeros((3, 3)))
    (cubic,) = explain(held, [CUBIC], x, y).effects
    assert cubic.removal == np.inf
    assert cubic.to_dict()["diverges_without"] is True and cubic.to_dict()["removal_share"] is None
    assert explain(exact(C), [CUBIC], x, y).effects[0].to_dict()["diverges_without"] is False


def test_the_transient_is_run_through_and_not_scored():
    x, y = record(C, seed=3)
    whole, cut = (explain(exact(C), [CUBIC], x, y, transient=t) for t in (0, 100))
    assert cut.first == 100
    np.testing.assert_allclose(cut.effects[0].series, whole.effects[0].series[99:])


def test_moving_average_noise_and_saturation_report_their_parameters():
    x, y = record(C, seed=4)
    limited = NARX(parse_terms(TERMS), np.array([A, B, C]), np.zeros((3, 3)), output_limits=(-1.0, np.inf))
    noise = effect("moving_average_noise", ("e[t-1]", "e[t-2]"), noise_lags=2)
    saturation = effect("output_saturation", ())
    explained = explain(limited, [noise, saturation], x, y, noise=np.array([0.4, -0.1]))
    ma, clipped = explained.effects
    assert ma.coefficients == (0.4, -0.1) and ma.share is None and ma.rms is None
    run = limited.simulate(x, y)[1:]
    assert clipped.limits == (-1.0, np.inf)
    assert clipped.at_limits == pytest.approx(np.mean(run <= -1.0))
    assert 0 < clipped.at_limits < 0.5
    unlimited = NARX(parse_terms(TERMS), np.array([A, B, C]), np.zeros((3, 3))).simulate(x, y)[1:]
    scale = np.sqrt(np.mean(y[1:] ** 2))
    assert clipped.removal == pytest.approx(np.sqrt(np.mean((unlimited - run) ** 2)) / scale)
    assert clipped.to_dict()["limits"] == [-1.0, None]
    # Neither brings terms to the process model: all three are the declared part's.
    assert explained.declared.terms == TERMS
