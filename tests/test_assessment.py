"""Judging a model on held-out records (models.assessment), against independent computations."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from models.assessment import assess
from models.errors import InputError
from models.narx import NARX
from models.terms import parse_terms

# y[t] = 2λ·y[t−1] − λ²·y[t−2] + x[t−1]: a double root at λ, slow as a high-order model's modes
# near one; an error δ in the state it starts from grows into a ramp t·λ^t·δ that peaks near
# 1/(1 − λ) samples at about 1/(e·(1 − λ)) times δ before it decays.
SLOW = 0.995
PERIOD, PERIODS = 4096, 5
NOISE_STD = 0.05


def slow_record(seed: int) -> tuple[NARX, np.ndarray, np.ndarray, np.ndarray]:
    """The model, a record of it from rest under a periodic input (five periods, the first its
    transient), the measured output (noise of std ``NOISE_STD`` added) and the noise-free one."""
    terms = tuple(parse_terms(["y[t-1]", "y[t-2]", "x[t-1]"]))
    model = NARX(terms, np.array([2 * SLOW, -(SLOW**2), 1.0]), np.zeros((3, 3)))
    rng = np.random.default_rng(seed)
    lines = np.arange(8, 80)  # a multisine of 72 lines, random phases
    t = np.arange(PERIOD)
    one = np.sum(
        np.cos(2 * np.pi * np.outer(t, lines) / PERIOD + rng.uniform(0, 2 * np.pi, lines.size)), axis=1
    )
    x = np.tile(0.01 * one / np.std(one), PERIODS)
    clean = signal.lfilter([0.0, 1.0], [1.0, -2 * SLOW, SLOW**2], x)  # from rest: no lfilter state
    return model, x, clean + NOISE_STD * rng.standard_normal(x.size), clean


def test_a_record_is_run_through_its_transient_from_its_start_and_scored_after_it() -> None:
    model, x, y, clean = slow_record(seed=5)
    assert np.std(clean[PERIOD:]) > 20 * NOISE_STD
    judged = assess(model, x, y, transient=PERIOD)
    # Independently: the model's response from rest (scipy's filter), scored after the first
    # period. The run started from the record's first two noisy readings differs from rest by a
    # ramp 0.995^t·t·δ, down to 10⁻⁵ of δ after 4096 samples.
    expected = float(np.sqrt(np.mean((clean[PERIOD:] - y[PERIOD:]) ** 2)))
    assert judged.free_run_rms == pytest.approx(expected, rel=1e-4)
    # Theory: what is left is the measurement noise, an RMS within 3 % of its std over 16 384 samples.
    assert judged.free_run_rms == pytest.approx(NOISE_STD, rel=0.03)
    # The one-step error is the noise filtered by 1 − 2λq⁻¹ + λ²q⁻², of variance (1 + 4λ² + λ⁴)σ².
    assert judged.one_step_rms == pytest.approx(NOISE_STD * np.sqrt(1 + 4 * SLOW**2 + SLOW**4), rel=0.03)


def test_started_from_measured_outputs_after_the_transient_the_noise_of_two_readings_lingers() -> None:
    """What F-16's multisines showed, on the slow model: the record cut after its transient and
    the free run started from the two noisy readings there carries their noise into the slow
    mode for about a thousand samples; run from the record's start, the model is judged on the
    noise alone. Over ten seeds the cut records' figure is several times the noise's."""
    ratios = []
    for seed in range(10):
        model, x, y, _ = slow_record(seed)
        whole = assess(model, x, y, transient=PERIOD).free_run_rms
        cut = assess(model, x[PERIOD:], y[PERIOD:]).free_run_rms
        ratios.append(cut / whole)
    assert np.median(ratios) > 5 and min(ratios) >= 1


@pytest.mark.parametrize(("transient", "message"), [(-1, "0 or more"), (5 * PERIOD, "judging a model needs")])
def test_a_transient_that_leaves_nothing_to_judge_is_refused(transient: int, message: str) -> None:
    model, x, y, _ = slow_record(seed=1)
    with pytest.raises(InputError, match=message):
        assess(model, x, y, transient=transient)
