"""The refined model's noise model, chosen after its process effects (models.noise_model)."""

from __future__ import annotations

import numpy as np
from scipy import signal

from models.narmax import moving_average
from models.narx import fit_narx
from models.refinement import refine
from models.scoring import NOISE_LAGS_OFFERED
from simulator.physics import PhysicalParameters
from simulator.simulate import Scenario, simulate
from simulator.theory import EXACT_TERMS, exact_narx

# The simulator's coloured force-sensor noise, as bench/planted.py plants it: 800 N of white ξ
# through C(q) = 1 + 1.5q⁻¹ + 1.2q⁻² + 0.9q⁻³ + 0.6q⁻⁴ + 0.3q⁻⁵, whose roots lie inside the unit
# circle (the largest at 0.91).
COLOUR = (1.5, 1.2, 0.9, 0.6, 0.3)
SENSOR_NOISE = 800.0


def test_a_moving_average_is_fitted_by_its_prediction_error_within_its_standard_errors():
    """Against the coefficients simulated, each within four of its asymptotic standard errors
    (the inverse of the information matrix E[ψψᵀ]/σ², ψ[t−i] = ξ[t−i]/C(q), computed from a long
    simulated ψ). Extended least squares' pseudo-linear regression, which needs 1/C − 1/2
    positive real, does not settle on this colour (tests/test_narmax.py)."""
    rng = np.random.default_rng(11)
    n = 6000
    xi = rng.standard_normal(n)
    colour = np.array(COLOUR)
    e = signal.lfilter(np.concatenate(([1.0], colour)), [1.0], xi)
    # Two records, so that no lag reaches from one to the next.
    estimate = moving_average([e[: n // 2], e[n // 2 :]], len(COLOUR))
    psi = signal.lfilter([1.0], np.concatenate(([1.0], colour)), rng.standard_normal(200_000))
    lagged = np.column_stack([psi[len(COLOUR) - i : psi.size - i] for i in range(1, len(COLOUR) + 1)])
    information = lagged.T @ lagged / lagged.shape[0]
    standard_errors = np.sqrt(np.diag(np.linalg.inv(information)) / n)
    z = (estimate - colour) / standard_errors
    assert np.all(np.abs(z) < 4), (estimate, z)


def test_noise_on_the_force_sensor_is_named_as_the_noise_model_and_leaves_the_free_run_alone():
    """The rig's own structure declared, its force read through coloured sensor noise (1600
    samples): the equation error is −b₁·n[t−4], a moving average of the planted colour. In the
    rounds the structure re-estimated with it by extended least squares ran free over the check
    blocks worse than without, and the loop refused it: nothing was named, and the model's
    one-step prediction error stayed at the noise's RMS, |b₁|·800 N·√(1 + Σc²), where |b₁|·800 N
    is what a prediction that knows the colour leaves. After the rounds the noise family's lags
    are significant on the residual, and the noise model is reported, the process's
    least-squares fit left as it was."""
    scenario = Scenario(x_noise_std=SENSOR_NOISE, noise_colour=COLOUR)
    record, other = simulate(scenario, 1600, 4), simulate(scenario, 4000, 50_004)
    result = refine([(record.x, record.y)], EXACT_TERMS)

    assert {effect.name for effect in result.effects_added} == {"moving_average_noise"}
    # One noise model, one round of the report, whatever number of offers its lags took.
    assert [step.criterion for step in result.kept] == ["whiteness"]
    assert result.noise.size >= len(COLOUR) > NOISE_LAGS_OFFERED
    assert result.kept[0].added.noise_lags == result.noise.size
    # The process is the rig's structure fitted by least squares on the record, untouched.
    assert result.estimator == "least squares"
    least_squares = fit_narx([(record.x, record.y)], EXACT_TERMS)
    np.testing.assert_allclose(result.refined.theta, least_squares.theta, rtol=1e-12)
    # On another record of the rig: the one-step prediction with the noise model is near what
    # the colour, known, leaves; without it, at the noise's own RMS.
    exact = exact_narx(PhysicalParameters())
    floor = abs(dict(zip(exact.term_names, exact.theta, strict=True))["x[t-4]"]) * SENSOR_NOISE
    residual = result.refined.residuals(other.x, other.y)
    predicted = signal.lfilter([1.0], np.concatenate(([1.0], result.noise)), residual)[100:]
    assert np.sqrt(np.mean(residual**2)) > 2 * floor
    assert np.sqrt(np.mean(predicted**2)) < 1.2 * floor
