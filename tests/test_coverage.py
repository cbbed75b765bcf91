"""How much of a test record lies outside its estimation records (models.coverage), against the
shares its construction fixes, and on the F-16 benchmark's records of another band."""

from __future__ import annotations

import numpy as np
import pytest

from harness.prerequisites import benchmark_file
from models.coverage import EXTRAPOLATING, WELCH_SAMPLES, Coverage, coverage
from models.errors import InputError
from recordfiles.reader import Layout, read_record

PERIOD = WELCH_SAMPLES  # a multisine of this period puts every line on a Welch bin


def multisine(lines: range, amplitude: float, periods: int, rng: np.random.Generator) -> np.ndarray:
    """Σ amplitude·cos(2π k t / PERIOD + φ_k) over the ``lines`` k, random phases: its power is
    amplitude²/2 a line. Lines three bins apart or more leave a Hann-windowed segment's power at
    exactly that (the square of the window has no component beyond two bins to mix them)."""
    t = np.arange(PERIOD * periods)
    phases = rng.uniform(0, 2 * np.pi, len(lines))
    return sum(
        amplitude * np.cos(2 * np.pi * k * t / PERIOD + phi) for k, phi in zip(lines, phases, strict=True)
    )


def test_the_share_of_power_outside_the_excited_band_is_the_power_of_the_lines_put_there():
    rng = np.random.default_rng(5)
    band, beyond = range(5, 101, 3), range(300, 396, 3)
    fitted = [(multisine(band, 1.0, 8, rng), np.zeros(PERIOD * 8)) for _ in range(2)]
    # 32 lines within the estimation band, as many at twice the amplitude far outside it: 4 units
    # of power outside for each one within.
    inside, outside = multisine(band, 1.0, 6, rng), multisine(beyond, 2.0, 6, rng)
    found = coverage(fitted, inside + outside, np.zeros(PERIOD * 6))
    assert found.outside_band == pytest.approx(len(beyond) * 4.0 / (len(band) + len(beyond) * 4.0), abs=1e-9)
    assert coverage(fitted, inside, np.zeros(PERIOD * 6)).outside_band < 1e-12
    assert found.extrapolates
    assert found.describe().startswith("80 % of its input's power outside the estimation records' band; ")


def test_the_shares_beyond_the_range_count_the_samples_outside_the_estimation_records_extremes():
    rng = np.random.default_rng(6)
    fitted = [
        (np.linspace(-1.0, 0.5, 5000), np.linspace(0.0, 2.0, 5000)),
        (np.linspace(-0.5, 1.0, 5000), np.zeros(5000)),
    ]
    x = rng.permutation(np.linspace(-2.0, 2.0, 4001))  # |x| > 1: 2000 of 4001 samples
    y = rng.permutation(np.linspace(-1.0, 2.0, 4001))  # y < 0: 1334 of them
    found = coverage(fitted, x, y)
    assert found.input_beyond == pytest.approx(2000 / 4001, abs=1e-12)
    assert found.output_beyond == pytest.approx(1334 / 4001, abs=1e-12)


def test_a_record_within_the_estimation_data_does_not_extrapolate():
    rng = np.random.default_rng(7)
    x = rng.standard_normal(20_000)
    fitted = [(x[:10_000], x[:10_000] ** 3)]
    found = coverage(fitted, 0.5 * x[10_000:], 0.1 * x[10_000:])
    assert found.input_beyond == 0.0 and found.output_beyond == 0.0 and found.outside_band < EXTRAPOLATING
    assert not found.extrapolates
    assert found.describe() == "within the estimation records' band and range"


def test_shares_at_the_threshold_are_within_and_above_it_extrapolate():
    at = Coverage(EXTRAPOLATING, EXTRAPOLATING, 0.0, 1.0)
    above = Coverage(0.0, 0.0, 2 * EXTRAPOLATING, 1.0)
    assert not at.extrapolates and above.extrapolates
    assert above.describe() == "2 % of its outputs beyond their range"


def test_the_input_scale_is_the_test_inputs_largest_magnitude_over_the_estimation_inputs():
    """Two estimation records whose inputs reach −3 and 2: a test input reaching 7.5 is 2.5 times
    their largest magnitude, one reaching 1.5 half of it."""
    rng = np.random.default_rng(9)
    fitted = [
        (np.array([0.5, -3.0, 1.0] * 200), rng.standard_normal(600)),
        (np.array([2.0, 0.0] * 300), rng.standard_normal(600)),
    ]
    assert coverage(fitted, np.array([1.0, 7.5, -2.0] * 200), rng.standard_normal(600)).input_scale == 2.5
    assert coverage(fitted, np.array([1.0, -1.5] * 300), rng.standard_normal(600)).input_scale == 0.5


def test_a_constant_estimation_input_leaves_every_frequency_unexcited():
    fitted = [(np.full(4096, 3.0), np.zeros(4096))]
    x = np.random.default_rng(8).standard_normal(4096)
    assert coverage(fitted, x, np.zeros(4096)).outside_band == pytest.approx(1.0)


def test_no_estimation_records_is_refused():
    with pytest.raises(InputError, match="needs the estimation records"):
        coverage([], np.zeros(100), np.zeros(100))


def test_the_f16_special_odd_multisines_lie_mostly_outside_the_full_grid_band():
    """The full-grid multisines excite 2–15 Hz; the special odd ones 1–60 Hz at 400 Hz. With a
    flat force spectrum, (60 − 15)/(60 − 1) = 76 % of the latter's power lies outside the former's
    band; within the band, the full grid's own test levels."""
    layout = Layout("Force", "Acceleration2")

    def signals(name: str) -> tuple[np.ndarray, np.ndarray]:
        record = read_record(benchmark_file("f16-gvt", name), layout)
        return record.x, record.y

    fitted = [signals(f"F16Data_FullMSine_Level{n}.csv") for n in (3, 5, 7)]
    for level in (1, 2, 3):
        odd = coverage(fitted, *signals(f"F16Data_SpecialOddMSine_Level{level}_Validation.csv"))
        assert odd.outside_band == pytest.approx((60 - 15) / (60 - 1), abs=0.03) and odd.extrapolates
    for level in (2, 4, 6):
        assert not coverage(fitted, *signals(f"F16Data_FullMSine_Level{level}_Validation.csv")).extrapolates
