"""Held-out validation errors (models.validation): one-step, k-step and free-run."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import DISTURBANCE_STD, exact_narx_residual, reference_coefficients

from models.errors import InputError
from models.narx import NARX, fit_narx
from models.terms import parse_terms
from models.validation import k_step_predictions, one_step_fit, validate
from simulator.simulate import Scenario, simulate
from simulator.theory import EXACT_TERMS, exact_narx


@pytest.fixture(scope="module")
def model(disturbed_record) -> NARX:
    return fit_narx([(disturbed_record.x, disturbed_record.y)], EXACT_TERMS)


@pytest.fixture(scope="module")
def held_out():
    return simulate(Scenario(disturbance_std=DISTURBANCE_STD), 3000, seed=91)


EPS = np.finfo(float).eps


def test_one_step_horizon_is_the_one_step_prediction(model, held_out) -> None:
    """The same sum φ[t]ᵀθ in another order: terms of size up to 6|y| (SPEC §2's AR part), so the
    two agree to a few eps·6·max|y|."""
    predicted = k_step_predictions(model, held_out.x, held_out.y, 1)
    assert np.all(np.isnan(predicted[:4]))
    bound = 10 * EPS * 6 * np.max(np.abs(held_out.y))
    np.testing.assert_allclose(predicted[4:], model.predict(held_out.x, held_out.y), rtol=0, atol=bound)


@pytest.mark.parametrize("steps", [2, 5, 17])
def test_k_step_prediction_equals_a_free_run_from_each_origin(model, held_out, steps) -> None:
    """ŷ[t|t−k] recomputed for sampled t by the model's own free run started at t−k with the
    measured outputs y[t−k−3 … t−k] as initial conditions and run to t. The two order their
    sums differently; the AR part, nearly (1 − q⁻¹)⁴, grows a rounding difference by ~k³/6 over
    k steps (~800 at k = 17), so they agree to ~1e-11 relative; 1e-9 is allowed."""
    predicted = k_step_predictions(model, held_out.x, held_out.y, steps)
    L = model.max_lag
    assert np.all(np.isnan(predicted[: L + steps - 1])) and not np.isnan(predicted[L + steps - 1])
    for t in range(L + steps - 1, 3000, 97):
        start = t - steps - L + 1
        segment = model.simulate(held_out.x[start : t + 1], held_out.y[start : start + L])
        assert predicted[t] == pytest.approx(segment[-1], rel=1e-9)


def test_errors_pool_the_records(model, held_out) -> None:
    other = simulate(Scenario(disturbance_std=DISTURBANCE_STD), 2000, seed=92)
    records = [(held_out.x, held_out.y), (other.x, other.y)]
    result = validate(model, records, steps=3)
    residuals = np.concatenate([model.residuals(x, y) for x, y in records])
    measured = np.concatenate([y[4:] for _, y in records])
    assert result.one_step.rms == pytest.approx(np.sqrt(np.mean(residuals**2)), rel=1e-12)
    assert result.one_step.nrmse == pytest.approx(result.one_step.rms / np.std(measured), rel=1e-12)
    assert result.one_step.samples == 2996 + 1996
    assert result.k_step.samples == 2994 + 1994 and result.steps == 3
    free = np.concatenate([model.simulate(x, y)[4:] - y[4:] for x, y in records])
    assert result.free_run.rms == pytest.approx(np.sqrt(np.mean(free**2)), rel=1e-12)
    # The errors grow with the horizon: the disturbance's response accumulates.
    assert result.one_step.rms < result.k_step.rms < result.free_run.rms
    document = result.to_dict()
    assert document["k_step"]["steps"] == 3 and set(document) == {"one_step", "k_step", "free_run"}


def test_exact_model_on_noise_free_data_has_rounding_errors(noise_free_record, params) -> None:
    rec = noise_free_record
    result = validate(exact_narx(params), [(rec.x[:5000], rec.y[:5000])], steps=10)
    assert result.one_step.nrmse < 1e-12
    assert result.k_step.nrmse < 1e-9
    assert result.free_run.nrmse < 1e-7  # SPEC §2's static gain ~3e6 amplifies rounding (test_narx)


def test_a_diverging_free_run_has_infinite_errors() -> None:
    model = NARX(parse_terms(["y[t-1]^2"]), np.array([2.0]), np.zeros((1, 1)))
    x = np.linspace(-1.0, 1.0, 100)
    y = np.r_[3.0, np.linspace(0.1, 0.2, 99)]
    result = validate(model, [(x, y)], steps=2)
    assert result.free_run.rms == np.inf and result.free_run.nrmse == np.inf
    assert np.isfinite(result.one_step.rms)


def test_bad_horizons_and_records_are_refused(model, held_out) -> None:
    with pytest.raises(InputError, match="horizon must be an integer >= 1, got 0"):
        k_step_predictions(model, held_out.x, held_out.y, 0)
    with pytest.raises(InputError, match="too short"):
        validate(model, [(held_out.x[:12], held_out.y[:12])], steps=10)
    with pytest.raises(InputError, match="NaN"):
        validate(model, [(held_out.x, np.r_[np.nan, held_out.y[1:]])])


def test_k_step_prediction_with_friction_and_a_sinusoid_equals_the_free_run() -> None:
    """The same identity for non-polynomial factors: a difference read across the origin (one
    lag measured, the other predicted), sign and abs of it, and a sinusoid of t from ``t0``."""
    terms = ["y[t-1]", "y[t-2]", "sign(dy[t-1])", "dy[t-2]*abs(dy[t-2])", "cos(2pi*0.03*t)", "x[t-1]"]
    model = NARX(parse_terms(terms), np.array([1.2, -0.5, -0.01, -0.3, 0.02, 0.4]), np.zeros((6, 6)))
    rng = np.random.default_rng(12)
    x = rng.normal(size=400)
    y = model.simulate(x, [0.0, 0.0, 0.0], t0=5) + rng.normal(scale=0.01, size=400)
    steps, L = 6, model.max_lag
    predicted = k_step_predictions(model, x, y, steps, t0=5)
    for t in range(L + steps - 1, 400, 13):
        start = t - steps - L + 1
        segment = model.simulate(x[start : t + 1], y[start : start + L], t0=5 + start)
        assert predicted[t] == pytest.approx(segment[-1], rel=1e-12, abs=1e-15)


def test_one_step_fit_is_the_exact_residual_and_its_autocorrelation(held_out, params) -> None:
    """The record page's Figure 3: with the exact coefficients (SPEC §2, derived independently in
    conftest) the residual is e[t] = y[t] − φ[t]ᵀθ, and φ_ee is statsmodels' biased ACF of it."""
    from statsmodels.tsa.stattools import acf

    coefficients = reference_coefficients(params)
    model = NARX(parse_terms(EXACT_TERMS), coefficients, np.zeros((8, 8)), 1.0, 0)
    fit = one_step_fit(model, held_out.x, held_out.y, lags=30, alpha=0.01)
    expected = exact_narx_residual(held_out.x, held_out.y, coefficients)
    np.testing.assert_allclose(fit.residual, expected, rtol=0, atol=1e-12 * np.abs(held_out.y).max())
    np.testing.assert_array_equal(fit.measured, held_out.y[4:])
    np.testing.assert_allclose(fit.predicted + fit.residual, fit.measured, rtol=0, atol=1e-15)
    np.testing.assert_allclose(fit.autocorrelation.values, acf(expected, nlags=30, fft=False)[1:], atol=1e-9)
    n = expected.size
    np.testing.assert_allclose(fit.autocorrelation.pointwise_band, 2.5758293035489 / np.sqrt(n) * np.ones(30))
