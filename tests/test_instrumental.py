"""Instrumental-variable estimates (models/instrumental.py) against theory.

The system y0 = q⁻¹/(1 − 1.5q⁻¹ + 0.7q⁻²)·x is measured as y = y0 + v, v white: least squares
regresses on the noisy past outputs and attenuates the autoregressive coefficients, while the
instruments (the past outputs of a model's free run, driven by x alone) are uncorrelated with v.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy import signal

from models.instrumental import fit_instrumental
from models.narx import fit_narx

TERMS = ["y[t-1]", "y[t-2]", "x[t-1]"]
TRUE = np.array([1.5, -0.7, 1.0])


def noisy_record(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """4000 samples of the system above, the output measured with noise of 40 % of its spread."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(4000)
    clean = signal.lfilter([0.0, TRUE[2]], [1.0, -TRUE[0], -TRUE[1]], x)
    return x, clean + 0.4 * np.std(clean) * rng.standard_normal(x.size)


def test_instrumental_variables_recover_what_least_squares_gets_wrong() -> None:
    x, y = noisy_record(11)
    least_squares = fit_narx([(x, y)], TERMS)
    estimate = fit_instrumental(least_squares, [(x, y, 0)])
    assert estimate is not None
    assert np.max(np.abs(least_squares.theta - TRUE)) > 0.3, least_squares.theta
    assert np.max(np.abs(estimate.theta - TRUE)) < 0.1, estimate.theta


def test_no_instruments_are_made_from_a_model_whose_free_run_diverges() -> None:
    x, y = noisy_record(12)
    unstable = replace(fit_narx([(x, y)], TERMS), theta=np.array([2.5, -1.0, 1.0]))
    assert fit_instrumental(unstable, [(x, y, 0)]) is None


def test_a_clipping_sensors_instruments_read_only_the_equations_clear_of_its_limits() -> None:
    """The system above, noise-free, read through a sensor that clips at half its output's
    range: the equations clear of the plateaus are exact, and the estimate from them is the
    system; on the plateaus the reading is not the output, and equations holding them bias it."""
    rng = np.random.default_rng(13)
    x = rng.standard_normal(4000)
    clean = signal.lfilter([0.0, TRUE[2]], [1.0, -TRUE[0], -TRUE[1]], x)
    limits = (-0.5 * np.max(np.abs(clean)), 0.5 * np.max(np.abs(clean)))
    y = np.clip(clean, *limits)
    sensor = fit_narx([(x, y)], TERMS, output_limits=limits, saturation="sensor")
    estimate = fit_instrumental(sensor, [(x, y, 0)])
    assert estimate is not None and estimate.output_limits == limits
    np.testing.assert_allclose(estimate.theta, TRUE, atol=1e-8)
