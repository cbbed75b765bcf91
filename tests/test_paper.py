"""The paper's results (SPEC §6) and the Monte Carlo checks beyond its ten runs.

The study runs once per session with the documented default settings
(:class:`simulator.study.StudySettings`); the assertions are the issue's acceptance criteria.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from simulator.paper import monte_carlo_checks, run_study
from simulator.study import StudySettings

SETTINGS = StudySettings()


@pytest.fixture(scope="module")
def study() -> dict:
    return run_study(SETTINGS).to_dict()


@pytest.fixture(scope="module")
def monte_carlo() -> dict:
    # 1000 records: the binomial sd of a 95 % coverage is then 0.7 %, a third of the ±2 % allowed.
    return monte_carlo_checks(SETTINGS, 1000)


def test_settings_reproduce_the_papers_sigma_k(study):
    """SPEC §6: a disturbance of a few percent of the excitation gives σ̂_k ≈ 0.07 at N = 2000."""
    assert SETTINGS.disturbance_std / SETTINGS.excitation_std < 0.05
    for name in ("I", "II"):
        assert 0.06 < study["cases"][name]["mean_sigma_k"] < 0.08


def test_case_i_healthy_is_rarely_detected(study):
    assert study["cases"]["I"]["detected"] <= 1


@pytest.mark.parametrize("name", ["II", "III"])
def test_k2_faults_are_detected_and_sized(study, name):
    case = study["cases"][name]
    assert case["detected"] == SETTINGS.runs
    assert abs(case["mean_k_hat"] - case["true_k"]) <= 0.05


@pytest.mark.parametrize("name", ["I", "II", "III"])
def test_k2_model_is_accepted_by_its_q_test(study, name):
    assert study["cases"][name]["accepted_k2"] >= 9


@pytest.mark.parametrize("name", ["II", "III"])
def test_k2_faults_are_localised_to_k2(study, name):
    """The k1 model cannot express a k2 fault (its residual variance is about twice the k2 model's
    at 3 %, far more at 29 %), so the k2 mode is the candidate in every run and the fault is
    localised to it exactly in the runs whose k2 Q test accepts: never to k1. Choosing the mode by
    the smallest Q instead sends some of these runs to k1, whose residual is white but larger."""
    case = study["cases"][name]
    assert set(case["fault_mode"]) <= {"k2", None}
    assert case["localised"] == case["accepted_k2"] >= 9


def test_case_iv_is_detected_rejected_by_k2_and_localised_to_k1(study):
    case = study["cases"]["IV"]
    assert case["detected"] == SETTINGS.runs
    assert case["accepted_k2"] == 0
    assert all(q > case["q_critical"] for q in case["q"])
    localised_and_covered = sum(
        mode == "k1" and low <= 30 <= high
        for mode, (low, high) in zip(case["fault_mode"], case["interval"], strict=True)
    )
    assert localised_and_covered >= 9


def test_k2_alone_detects_case_iv_and_how_that_depends_on_noise(study):
    """The k2 model cannot express a k1 fault. Its k̂ settles on a small bias, which the
    magnitude test detects only while σ̂_k (proportional to the disturbance) is small; its
    residual is far from white, by a margin that shrinks as the noise grows. At the study's
    noise level (σ̂_k ≈ 0.07, as in the paper) the chain detects the fault in every run."""
    rows = study["case_iv_k2_alone_detection_vs_noise"]
    levels = [row["disturbance_std"] for row in rows]
    assert levels == sorted(levels)
    assert [row["mean_sigma_k"] for row in rows] == sorted(row["mean_sigma_k"] for row in rows)
    assert [row["mean_q"] for row in rows] == sorted((row["mean_q"] for row in rows), reverse=True)
    assert rows[0]["magnitude_test_detects"] >= 9
    assert rows[-1]["magnitude_test_detects"] < rows[0]["magnitude_test_detects"]
    at_study_level = next(row for row in rows if row["disturbance_std"] == SETTINGS.disturbance_std)
    assert at_study_level["detected"] == SETTINGS.runs
    assert study["cases"]["IV"]["detected_by_k2_alone"] == SETTINGS.runs


@pytest.mark.slow  # the 1000-record Monte Carlo study: `make slow`
def test_false_alarm_rate_is_at_most_alpha(monte_carlo):
    records = monte_carlo["records"]
    assert records >= 500
    # The count of false alarms must be one a Binomial(n, α) produces with 95 % probability.
    assert monte_carlo["false_alarms"] <= stats.binom.ppf(0.95, records, SETTINGS.alpha)


@pytest.mark.slow  # the 1000-record Monte Carlo study: `make slow`
def test_intervals_cover_the_true_magnitude(monte_carlo):
    true_k = np.array([row["true_k"] for row in monte_carlo["faulty"]])
    # Faulty records span the whole range, both ends included.
    assert true_k.min() < -28 and true_k.max() > 28
    assert 0.93 <= monte_carlo["coverage_with_model_term"] <= 0.97


@pytest.mark.slow  # the 1000-record Monte Carlo study: `make slow`
def test_model_term_widens_intervals_where_the_model_is_least_certain(monte_carlo):
    rows = monte_carlo["faulty"]
    ratio = np.array([row["sigma_k"] / row["sigma_k_record"] for row in rows])
    assert np.all(ratio >= 1.0)
    ends = np.array([abs(row["true_k"]) > 24 for row in rows])
    assert ratio[ends].mean() > ratio[~ends].mean()
    assert monte_carlo["coverage_with_model_term"] >= monte_carlo["coverage_paper_sigma"]
