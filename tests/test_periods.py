"""The noise between the periods of a periodic experiment (models.periods)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from harness.multisines import FILTER, PERIOD, measured
from models.periods import PeriodNoise, period_noise, pooled_period_noise
from models.refinement import refine


def test_the_noise_between_periods_is_the_noise_added_to_the_output():
    """σ̂ agrees with the σ added, within three of its standard errors σ/√(2·P(M − 1)); the first
    of several periods, which holds the start-up transient, is left out."""
    x, clean, y = measured(periods=6, sigma=0.05, seed=1)
    noise = period_noise(x, y)
    assert noise is not None
    assert (noise.period, noise.periods, noise.dof) == (PERIOD, 5, PERIOD * 4)
    assert abs(noise.rms - 0.05) < 3 * 0.05 / np.sqrt(2 * noise.dof)
    assert noise.standard_error == pytest.approx(noise.rms / np.sqrt(2 * noise.dof))
    # The transient the first period holds would have been taken for noise.
    first = clean[:PERIOD] - clean[PERIOD : 2 * PERIOD]
    assert np.max(np.abs(first)) > 0.05


def test_two_periods_are_both_used_and_samples_after_the_last_whole_period_left_out():
    x, _, y = measured(periods=3, sigma=0.2, seed=2)
    x, y = x[PERIOD:], y[PERIOD:]  # two steady periods
    tail = 100
    noise = period_noise(np.concatenate([x, x[:tail]]), np.concatenate([y, y[:tail] + 5.0]))
    assert noise is not None and (noise.periods, noise.period) == (2, PERIOD)
    by_hand = np.sqrt(np.sum((y[:PERIOD] - y[PERIOD:]) ** 2 / 2) / PERIOD)  # Σ_m (y_m − ȳ)² for M = 2
    assert noise.rms == pytest.approx(by_hand)


@pytest.mark.parametrize(
    "make_x",
    [
        pytest.param(lambda t, rng: rng.standard_normal(t.size), id="random"),
        pytest.param(lambda t, rng: signal.chirp(t, 0.001, t[-1], 0.2), id="swept sine"),
        pytest.param(lambda t, rng: np.sin(2 * np.pi * t / (0.7 * t.size)), id="slower than half the record"),
        pytest.param(lambda t, rng: np.ones(t.size), id="constant"),
    ],
)
def test_an_input_that_does_not_repeat_gives_no_noise_floor(make_x):
    rng = np.random.default_rng(3)
    t = np.arange(4096.0)
    x = make_x(t, rng)
    assert period_noise(x, x + rng.standard_normal(t.size)) is None


def test_pooled_noise_weights_each_record_by_its_degrees_of_freedom():
    x1, _, y1 = measured(periods=3, sigma=0.1, seed=4)
    x2, _, y2 = measured(periods=5, sigma=0.3, seed=5)
    one, two = period_noise(x1, y1), period_noise(x2, y2)
    assert one is not None and two is not None
    pooled = pooled_period_noise([(x1, y1), (x2, y2)])
    expected = np.sqrt((one.rms**2 * one.dof + two.rms**2 * two.dof) / (one.dof + two.dof))
    assert pooled == PeriodNoise(pytest.approx(expected), 2 + 4, PERIOD, one.dof + two.dof)
    # A floor must hold for every record it judges: one that does not repeat gives none.
    rng = np.random.default_rng(6)
    assert pooled_period_noise([(x1, y1), (rng.standard_normal(2000), rng.standard_normal(2000))]) is None


def test_part_of_a_free_run_above_the_floor():
    """√(rms² − σ̂²), and zero within two standard errors of σ̂² (4·σ̂·se(σ̂))."""
    floor = PeriodNoise(0.1, 3, 100, 200)
    assert floor.beneath(0.2) == pytest.approx(np.sqrt(0.2**2 - 0.1**2))
    assert floor.beneath(np.sqrt(0.1**2 + 3.9 * 0.1 * floor.standard_error)) == 0.0
    assert floor.beneath(0.09) == 0.0


def test_the_loop_reports_the_noise_floor_of_the_checked_records():
    """A linear system driven by a multisine, measured with white output noise: the right linear
    model's free run over the check blocks is at the noise floor, which the report gives. Four
    periods after the transient: the loop runs on three, the fourth held out."""
    records = [measured(periods=5, sigma=0.3, seed=seed) for seed in (7, 8)]
    result = refine(
        [(x[PERIOD:], y[PERIOD:]) for x, _, y in records], ["y[t-1]", "y[t-2]", "x[t-1]", "x[t-2]"]
    )
    floor = result.noise_floor
    assert floor is not None and (floor.periods, floor.period) == (3 + 3, PERIOD)  # the first of 4 left out
    assert abs(floor.rms - 0.3) < 3 * floor.standard_error
    assert floor.beneath(result.check_rms) == 0.0, (result.check_rms, floor)
    # Where the records do not repeat there is no floor to report.
    rng = np.random.default_rng(9)
    x = rng.standard_normal(3000)
    y = signal.lfilter(*FILTER, x) + 0.3 * rng.standard_normal(x.size)
    assert refine([(x, y)], ["y[t-1]", "y[t-2]", "x[t-1]", "x[t-2]"]).noise_floor is None
