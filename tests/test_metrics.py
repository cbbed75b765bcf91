"""RMS and NRMSE against their definitions, and on models whose quality is known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from models.errors import InputError
from models.metrics import nrmse, rms
from simulator.physics import PhysicalParameters
from simulator.simulate import Scenario, simulate
from simulator.theory import exact_narx


def test_rms_of_a_known_series():
    assert rms([3.0, -4.0]) == pytest.approx(math.sqrt(12.5), rel=1e-15)


def test_nrmse_is_zero_for_a_perfect_and_one_for_the_mean_prediction():
    y = np.random.default_rng(0).normal(5.0, 2.0, 1000)
    assert nrmse(y, y) == 0.0
    assert nrmse(y, np.full_like(y, y.mean())) == pytest.approx(1.0, rel=1e-12)


def test_exact_model_predicts_and_simulates_noise_free_data():
    record = simulate(Scenario(), 5000, seed=4)
    model = exact_narx(PhysicalParameters())
    one_step = model.predict(record.x, record.y)
    assert nrmse(record.y[4:], one_step) < 1e-12
    # Free run accumulates rounding through the static gain 1/(1 − Σa) ≈ 3e6, so it is looser.
    assert nrmse(record.y, model.simulate(record.x, record.y)) < 1e-6


def test_nrmse_of_a_diverged_simulation_is_infinite():
    assert nrmse([1.0, 2.0, 3.0], [1.0, np.nan, np.nan]) == math.inf


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: rms([]), "empty"),
        (lambda: nrmse([1.0, 1.0], [1.0, 2.0]), "constant"),
        (lambda: nrmse([1.0, 2.0], [1.0]), "differ in shape"),
    ],
)
def test_bad_input_is_refused(call, message):
    with pytest.raises(InputError, match=message):
        call()
