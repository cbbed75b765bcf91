"""The default alarm rules on simulated streams through the real inspection chain (bench/alarms.py).

The slow test is the bench's study at a reduced size: healthy structure-years, each structure with
fault-mode models of its own, and a drift of 0.5 % a day in k2. Its false-alarm counts are held to
the ranges the designs themselves give (no tolerance chosen here); the CUSUM must call the drift
sooner than the persistence rule. The fast test runs the same chain on a few drifting structures.
"""

import numpy as np
import pytest
from scipy import stats

from bench.alarms import RECORDS_PER_YEAR, SETTINGS, cusum_count_range, drift_study, healthy_study
from models.alarms import persistence_alarm_rate


@pytest.mark.slow
def test_false_alarms_per_structure_year_are_the_designs_and_the_cusum_calls_a_drift_first():
    structures, years = 8, 1.0
    healthy = healthy_study(structures, years, seed=11, progress=False)
    records = round(years * RECORDS_PER_YEAR)
    low, high = cusum_count_range(healthy.designs, records, 0.99, seed=11)
    assert low <= healthy.counts["cusum"] <= high, (healthy.counts, low, high)
    # Verdicts flagged at no more than α (binomial), and persistence alarms no more than its
    # design at α gives (Poisson, one-sided at 99.5 %: excess is what would be wrong).
    assert healthy.counts["record"] <= stats.binom.ppf(0.995, healthy.records, SETTINGS.alpha)
    expected = persistence_alarm_rate(SETTINGS.alpha, 3, 5) * healthy.records
    assert healthy.counts["persistence"] <= stats.poisson.ppf(0.995, expected), (healthy.counts, expected)

    drift = drift_study(30, 0.5, horizon_days=3.0, seed=11, progress=False)
    assert np.isfinite(drift.delays["cusum"]).all() and np.isfinite(drift.delays["persistence"]).all()
    assert drift.median("cusum") < drift.median("persistence"), drift.delays


def test_every_rule_calls_a_half_percent_a_day_drift_within_two_days():
    drift = drift_study(4, 0.5, horizon_days=2.0, seed=12, progress=False)
    for rule, delays in drift.delays.items():
        assert np.all(delays <= 2.0), (rule, delays)
    # Four records a day: a delay is a whole number of quarter days after the onset.
    assert np.allclose(drift.delays["cusum"] * 4, np.round(drift.delays["cusum"] * 4))
    assert drift.median("cusum") <= drift.median("persistence")
