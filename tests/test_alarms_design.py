"""The alarm rules of models/alarms.py against independent computations.

The CUSUM's run lengths are checked against a Monte Carlo of the chart on N(0, 1) (and N(δ, 1)),
against published table values and against Siegmund's approximation; the persistence rule's
onset rate against a simulation of independent flags.
"""

import numpy as np
import pytest

from models.alarms import (
    CusumDesign,
    common_share,
    cusum,
    cusum_chart,
    default_rules,
    design_cusum,
    in_control_arl,
    one_sided_arl,
    persistence,
    persistence_alarm_rate,
    severity,
    siegmund_arl,
    two_sided_arl,
)
from models.errors import InputError


def simulated_run_lengths(design: CusumDesign, mean: float, runs: int, seed: int) -> np.ndarray:
    """Run lengths of `runs` independent two-sided charts on z ~ N(mean, 1), all stepped at once."""
    rng = np.random.default_rng(seed)
    upper = np.zeros(runs)
    lower = np.zeros(runs)
    lengths = np.zeros(runs, dtype=int)
    active = np.arange(runs)
    t = 0
    while active.size:
        t += 1
        z = rng.standard_normal(active.size) + mean
        upper[active] = np.maximum(0.0, upper[active] + z - design.reference)
        lower[active] = np.maximum(0.0, lower[active] - z - design.reference)
        done = (upper[active] > design.threshold) | (lower[active] > design.threshold)
        lengths[active[done]] = t
        active = active[~done]
    return lengths


def assert_mean_consistent(lengths: np.ndarray, expected: float) -> None:
    """The sample mean within four standard errors of the computed ARL."""
    standard_error = lengths.std(ddof=1) / np.sqrt(lengths.size)
    assert abs(lengths.mean() - expected) < 4.0 * standard_error, (lengths.mean(), expected, standard_error)


def test_integral_equation_matches_published_tables():
    # Hawkins & Olwell (1998), Table 3.1 / Lucas (1976): h = 5, k = 0.5 → 930.9 in control, 10.38 at δ = 1;
    # h = 4, k = 0.5 → 336 and 8.38.
    assert one_sided_arl(5.0, 0.5, 0.0) == pytest.approx(930.9, abs=0.5)
    assert one_sided_arl(5.0, 0.5, 1.0) == pytest.approx(10.38, abs=0.01)
    assert one_sided_arl(4.0, 0.5, 0.0) == pytest.approx(336.0, abs=1.0)
    assert one_sided_arl(4.0, 0.5, 1.0) == pytest.approx(8.38, abs=0.01)


@pytest.mark.parametrize("h, r, mu", [(4.0, 0.5, 0.0), (6.0, 0.5, 0.0), (5.0, 0.25, 0.5), (3.0, 0.5, 1.5)])
def test_integral_equation_agrees_with_siegmund(h, r, mu):
    # Siegmund's approximation is good to a few per cent here; the integral equation is exact.
    assert one_sided_arl(h, r, mu) == pytest.approx(siegmund_arl(h, r, mu), rel=0.03)


def test_design_reaches_its_target_and_grows_with_it():
    design = design_cusum(1460.0, shift=1.0)
    assert design.reference == 0.5
    assert two_sided_arl(design.threshold, 0.5, 0.0) == pytest.approx(1460.0, rel=1e-8)
    assert design.arl_at_shift == pytest.approx(two_sided_arl(design.threshold, 0.5, 1.0))
    assert design_cusum(2920.0, 1.0).threshold > design.threshold > design_cusum(365.0, 1.0).threshold
    # A larger design shift: a larger reference and a shorter run length at that shift.
    assert design_cusum(1460.0, shift=2.0).arl_at_shift < design.arl_at_shift


def test_in_control_run_length_matches_monte_carlo():
    design = design_cusum(200.0, shift=1.0)
    lengths = simulated_run_lengths(design, mean=0.0, runs=4000, seed=1)
    assert_mean_consistent(lengths, 200.0)


def test_run_length_at_the_design_shift_matches_monte_carlo():
    design = design_cusum(1460.0, shift=1.0)
    for mean in (1.0, -1.0, 0.5):
        lengths = simulated_run_lengths(design, mean=mean, runs=4000, seed=2)
        assert_mean_consistent(lengths, two_sided_arl(design.threshold, design.reference, mean))


def test_cusum_alarms_where_the_recursion_crosses_and_dates_the_drift():
    design = design_cusum(1460.0, shift=1.0)
    z = np.zeros(80)
    z[50:] = -2.0  # a step of −2σ from record 50: S⁻ grows by 1.5 a record
    path = cusum(z, design)
    first = 50 + int(np.floor(design.threshold / 1.5))  # first i with 1.5·(i − 49) > h
    assert path.alarm_at == first
    assert path.drift_start == 50
    assert np.all(path.upper == 0.0)
    assert path.lower[first] == pytest.approx(1.5 * (first - 49))
    assert path.lower[first - 1] <= design.threshold


def test_cusum_drift_start_after_the_last_zero_of_the_alarming_side():
    design = design_cusum(100.0, shift=1.0)
    z = np.array([0.0, 3.0, -4.0, 1.0, 2.0, 2.0, 2.0, 2.0])
    path = cusum(z, design)
    # S⁺: 0, 2.5, 0, 0.5, 2.0, 3.5, 5.0 ...; S⁺ last zero before the alarm is record 2.
    assert path.upper[2] == 0.0 and path.upper[1] == pytest.approx(2.5)
    assert path.alarm_at is not None and path.upper[path.alarm_at] > design.threshold
    assert path.drift_start == 3


def test_the_restarting_chart_is_the_recursion_started_afresh_after_each_alarm():
    # Independent computation: the one-alarm recursion run again from the record after each
    # alarm, on a stream with steps both ways and long quiet stretches.
    design = design_cusum(200.0, shift=1.0)
    rng = np.random.default_rng(7)
    z = rng.standard_normal(600) + np.repeat([0.0, 1.5, 0.0, -2.0, 0.3, 0.0], 100)
    chart = cusum_chart(z, design)
    alarms, drift_starts, statistic, start = [], [], [], 0
    while start < z.size:
        path = cusum(z[start:], design)
        end = z.size - start if path.alarm_at is None else path.alarm_at + 1
        statistic += np.maximum(path.upper[:end], path.lower[:end]).tolist()
        if path.alarm_at is None:
            break
        alarms.append(start + path.alarm_at)
        drift_starts.append(start + path.drift_start)
        start += path.alarm_at + 1
    assert len(alarms) >= 10  # the steps make the chart signal again and again
    assert chart.alarms == tuple(alarms)
    assert chart.drift_starts == tuple(drift_starts)
    np.testing.assert_array_equal(chart.statistic, statistic)
    with pytest.raises(InputError, match="finite"):
        cusum_chart([0.1, np.inf], design)


def test_cusum_without_alarm_and_bad_input():
    path = cusum(np.zeros(10), design_cusum(100.0))
    assert path.alarm_at is None and path.drift_start is None
    with pytest.raises(InputError, match="finite"):
        cusum([0.1, np.nan], design_cusum(100.0))
    with pytest.raises(InputError, match="one record"):
        design_cusum(0.5)
    with pytest.raises(InputError, match="positive"):
        design_cusum(100.0, shift=0.0)


def test_persistence_counts_k_of_the_last_m():
    assert persistence([True, True, True], 3, 5)
    assert not persistence([True, True], 3, 5)
    assert not persistence([True, True, True, False, False, False], 3, 5)  # the first True left the window
    assert persistence([True, True, True, False, False], 3, 5)
    with pytest.raises(InputError, match="k ≤ m"):
        persistence([True], 4, 3)
    with pytest.raises(InputError, match="k ≤ m"):
        persistence([True], 0, 3)


def test_persistence_onset_rate_matches_simulated_flags():
    rng = np.random.default_rng(3)
    alpha, k, m, n = 0.2, 3, 5, 100_000
    flags = rng.random(n) < alpha
    holds = np.array([persistence(flags[max(0, i - m + 1) : i + 1], k, m) for i in range(n)])
    onsets = int(np.sum(holds[1:] & ~holds[:-1]))
    expected = persistence_alarm_rate(alpha, k, m) * (n - 1)
    # Onsets are rarer than records and nearly independent: a Poisson bound of four standard deviations.
    assert abs(onsets - expected) < 4.0 * np.sqrt(expected), (onsets, expected)


def test_severity_is_sign_aware():
    assert severity(-0.09, -0.06, -0.05)
    assert not severity(-0.09, -0.04, -0.05)
    assert severity(0.06, 0.08, 0.05)
    assert not severity(0.04, 0.08, 0.05)
    assert not severity(0.06, 0.08, -0.05)  # a gain is no loss
    with pytest.raises(InputError, match="non-zero"):
        severity(-0.1, 0.1, 0.0)
    with pytest.raises(InputError, match="above"):
        severity(0.1, -0.1, 0.05)


def test_default_rules_spread_one_false_alarm_a_year_over_the_modes():
    rules = default_rules(records_per_day=4.0, modes=2)
    assert rules.cusum.arl_in_control == pytest.approx(2 * 1460.0)
    assert rules.cusum.reference == 1.0  # tuned to a step of 2σ
    assert two_sided_arl(rules.cusum.threshold, rules.cusum.reference, 0.0) == pytest.approx(2920.0, rel=1e-8)
    shared = default_rules(records_per_day=4.0, modes=2, common_share=0.06)
    assert shared.cusum.common_share == 0.06
    assert in_control_arl(shared.cusum.threshold, 1.0, 0.06) == pytest.approx(2920.0, rel=1e-8)
    assert (rules.persistence_k, rules.persistence_m) == (3, 5)
    assert default_rules(records_per_day=24.0).cusum.threshold > default_rules().cusum.threshold
    with pytest.raises(InputError, match="record rate"):
        default_rules(records_per_day=0.0)


def simulated_alarm_rate(design: CusumDesign, share: float, structures: int, records: int, seed: int):
    """Alarms per record of charts restarted after each alarm, one per structure with its own
    common offset β ~ N(0, c) and z_i = β + √(1 − c)·ε_i; the rate of each structure."""
    rng = np.random.default_rng(seed)
    offsets = np.sqrt(share) * rng.standard_normal(structures)
    upper = np.zeros(structures)
    lower = np.zeros(structures)
    alarms = np.zeros(structures)
    for _ in range(records):
        z = offsets + np.sqrt(1.0 - share) * rng.standard_normal(structures)
        upper = np.maximum(0.0, upper + z - design.reference)
        lower = np.maximum(0.0, lower - z - design.reference)
        alarmed = (upper > design.threshold) | (lower > design.threshold)
        alarms += alarmed
        upper[alarmed] = 0.0
        lower[alarmed] = 0.0
    return alarms / records


def test_averaged_in_control_arl_matches_monte_carlo_over_structures():
    # The fleet's false-alarm rate with a common offset per structure, against the quadrature.
    design = design_cusum(300.0, shift=2.0, common_share=0.1)
    rates = simulated_alarm_rate(design, 0.1, structures=3000, records=3000, seed=4)
    standard_error = rates.std(ddof=1) / np.sqrt(rates.size)
    assert abs(rates.mean() - 1.0 / 300.0) < 4.0 * standard_error, (rates.mean(), standard_error)
    # Ignoring the common offset would be wrong by far more than that.
    naive = design_cusum(300.0, shift=2.0)
    assert 1.0 / in_control_arl(naive.threshold, 1.0, 0.1) > 1.0 / 300.0 + 20.0 * standard_error


def test_common_share_is_the_model_part_of_sigma_k():
    assert common_share(0.1, 0.08) == pytest.approx(0.36)
    assert common_share(0.1, 0.1) == 0.0
    with pytest.raises(InputError, match="positive"):
        common_share(0.0, 0.0)
    with pytest.raises(InputError, match=r"\[0, 1\)"):
        in_control_arl(5.0, 0.5, 1.0)


def test_run_lengths_beyond_resolution_are_never_not_garbage():
    # At h = 46 the in-control chart's ARL is astronomically long; I − K is singular to working
    # precision and a plain solve returns a negative number.
    assert one_sided_arl(46.0, 0.5, 0.0) == np.inf
    assert two_sided_arl(100.0, 1.0, 0.3) == np.inf
    # Exactly singular, not only to working precision: a large reference and common share (the
    # stateful fuzz's alarm rules found it, as a 500 from an inspection).
    assert in_control_arl(16.0, 10.0, 0.9) == np.inf
    # Long intervals get nodes enough: ARL at μ = 1.1 against r = 1 grows linearly with h.
    assert one_sided_arl(60.0, 1.0, 1.1) == pytest.approx(siegmund_arl(60.0, 1.0, 1.1), rel=0.01)
    with pytest.raises(InputError, match="beyond any service"):
        design_cusum(1e12)


def test_a_shift_too_large_for_any_threshold_is_refused_with_a_message():
    """With a reference of 5.8 σ one record beyond it happens once in ~3·10⁸: even h = 0 runs
    longer than a year of records, and the design says so (Brent's bracket used to raise)."""
    with pytest.raises(InputError, match="no CUSUM threshold fits"):
        design_cusum(1460.0, shift=11.6)
