"""Fault modes under sensor noise (models/free_run_inspection.py): the accelerometer chain with
1 % noise on both measured signals, its fault modes trained from simulated experiments at known
magnitudes. The paper's chain (one-step residual, Ljung–Box localisation) fails there; the
free-run chain localises the fault and sizes it with an interval that covers the truth at the
designed rate."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from harness.accelerometer import ALPHA, record, scenario
from harness.noisy_modes import (
    FAR_MAGNITUDES,
    MAGNITUDES,
    TERMS,
    equation_error_modes,
    experiments,
    free_run_modes,
    perfect_sigma_k,
    slope_against_truth,
)
from models.errors import InputError
from models.free_run_inspection import UNDETERMINED_SHARE, FreeRunMode, fit_free_run_modes, inspect_free_run
from models.inspection import inspect
from models.output_error import estimated_start_error, without_cancelled_poles

TEST_LEVEL = 1e-3  # the chance a correct chain fails a rate assertion
SAMPLES = 4000
COVERAGE = 1 - ALPHA  # the interval k̂ ± z_{1−α/2}·σ̂_k
# The coverage test's training sets and the records inspected with each.
TRAININGS, RECORDS = 5, 40


@pytest.fixture(scope="module")
def modes() -> list[FreeRunMode]:
    """Both springs' modes from training set 61 000, whose searches end with a cancelled pole
    and zero and are searched again without them
    (:func:`test_the_healthy_point_simulates_the_chain_closer_than_the_far_spring_moves_it`): the
    tests that read these modes hold for any training set, that one too."""
    return free_run_modes(seed=61_000)


def faulty_records(
    count: int, seed: int, spring: str = "k2", magnitudes: tuple[float, float] = (4.0, 12.0)
) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """``spring`` loosened by magnitudes spread over ``magnitudes`` (percent), one record each."""
    drawn = np.random.default_rng(seed).uniform(*magnitudes, count)
    return [(k, *record(scenario(spring, float(k)), SAMPLES, seed + i)) for i, k in enumerate(drawn)]


def covers(verdict, k: float) -> bool:
    return verdict.interval is not None and verdict.interval[0] <= k <= verdict.interval[1]


def test_the_paper_chain_neither_localises_nor_covers_under_sensor_noise() -> None:
    """The finding reproduced: the one-step residual is coloured for every mode, so no mode is
    accepted, and the fault is an unknown one with no magnitude."""
    models = equation_error_modes()
    verdicts = [(k, inspect(x, y, models, alpha=ALPHA)) for k, x, y in faulty_records(5, 70_000)]
    assert all(v.status == "unknown_fault" for _, v in verdicts)
    assert not any(covers(v, k) for k, v in verdicts)


def test_a_loosened_spring_localised_and_sized_despite_sensor_noise(modes) -> None:
    """Localised, and sized: the near spring's magnitude is determined, so every verdict that
    names it gives an interval. Whether the intervals cover at the designed rate is judged over
    several training sets (below): with one, every record shares its modes' error."""
    verdicts = [inspect_free_run(x, y, modes, alpha=ALPHA) for _, x, y in faulty_records(40, 80_000)]
    localised = [v for v in verdicts if v.status == "faulty" and v.fault_mode == "k2"]
    assert len(localised) >= 0.9 * len(verdicts)
    assert all(v.interval is not None for v in localised)
    assert all(v.lags is None and len(v.modes) == 2 for v in verdicts)


def coverage_lower_bound(records: int, trainings: int, model_share: float) -> float:
    """The least count of covering intervals a chain whose σ̂_k is right gives at TEST_LEVEL, over
    ``trainings`` training sets of ``records`` records each.

    Records inspected with one training set's modes share its estimation error, so their
    coverages are correlated and the count is not binomial: for two of them the standardised
    errors are Gaussian with correlation at most ``model_share``, the share of σ̂²_k the modes'
    own error claims (at most: the error moves k̂ alike at every magnitude only in the worst
    case). The count's variance is then T·(R·p·q + R·(R − 1)·c), c the covariance of two
    coverages, and the bound its normal quantile.
    """
    z = stats.norm.ppf(1 - ALPHA / 2)
    pair = stats.multivariate_normal([0.0, 0.0], [[1.0, model_share], [model_share, 1.0]])
    both = pair.cdf([z, z]) - pair.cdf([-z, z]) - pair.cdf([z, -z]) + pair.cdf([-z, -z])
    variance = trainings * (
        records * COVERAGE * (1 - COVERAGE) + records * (records - 1) * (both - COVERAGE**2)
    )
    return trainings * records * COVERAGE - stats.norm.ppf(1 - TEST_LEVEL) * np.sqrt(variance)


@pytest.mark.slow  # five mode trainings and 200 records: `make slow`
def test_the_interval_covers_at_the_designed_rate_over_training_sets() -> None:
    """200 records, 40 for each of five training sets of the near spring's mode, at seeds and
    magnitudes (3 … 13 %) of their own. The count is judged against the bound a right σ̂_k gives
    (:func:`coverage_lower_bound`): with the modes' own error a tenth of σ̂²_k, an interval that
    covers 88 % of the time fails this with a chance of about 3 in 4 (84 % were the records
    independent), one that covers 90 % with about 2 in 5."""
    covered, shares = 0, []
    for training in range(TRAININGS):
        modes = free_run_modes(("k2",), seed=700_000 + 1000 * training)
        for k, x, y in faulty_records(RECORDS, 710_000 + 1000 * training, magnitudes=(3.0, 13.0)):
            verdict = inspect_free_run(x, y, modes, alpha=ALPHA)
            covered += covers(verdict, k)
            mode = verdict.mode("k2")
            shares.append(1 - (mode.sigma_k_record / mode.sigma_k) ** 2)
    assert covered >= coverage_lower_bound(RECORDS, TRAININGS, float(np.mean(shares)))


def test_one_training_sets_interval_is_right_in_each_part(modes) -> None:
    """One training set's σ̂_k judged part by part over 40 records at one magnitude: the count of
    covering intervals tells little there, the records sharing the modes' error (a few dozen of
    them cover a few fewer or more than the designed rate by chance far more often than
    independent records would).

    σ̂_k,record: every record's k̂ misses by its own error plus the training set's, alike at one
    magnitude, so k̂'s spread about its mean, standardised by σ̂_k,record, is χ²(R − 1) when that
    part is right; a σ̂_k,record two thirds of the truth fails this about three times in four. The
    mode's own part: the mean of k̂ misses the truth by the training set's error, which
    σ̂²_k − σ̂²_k,record claims, plus the records' own averaged."""
    k = 12.0
    estimates = [
        inspect_free_run(*record(scenario("k2", k), SAMPLES, 60_000 + i), modes[:1], alpha=ALPHA).mode("k2")
        for i in range(RECORDS)
    ]
    errors = np.array([mode.k_hat - k for mode in estimates])
    own = np.array([mode.sigma_k_record for mode in estimates])
    shared = np.array([mode.sigma_k**2 - mode.sigma_k_record**2 for mode in estimates])
    standardised = errors / own
    spread = float(np.sum((standardised - standardised.mean()) ** 2))
    low, high = stats.chi2.ppf([TEST_LEVEL / 2, 1 - TEST_LEVEL / 2], RECORDS - 1)
    assert low <= spread <= high
    miss = abs(float(errors.mean()))
    assert miss <= stats.norm.ppf(1 - TEST_LEVEL / 2) * np.sqrt(shared.mean() + np.mean(own**2) / RECORDS)


def test_healthy_records_are_not_found_faulty_beyond_the_designed_rate(modes) -> None:
    """With the near spring's mode, whose detection the records decide (the far spring's mode's
    own error is most of its σ̂_k, so its z is small whatever the record)."""
    verdicts = [
        inspect_free_run(*record(scenario(), SAMPLES, 90_000 + i), modes[:1], alpha=ALPHA) for i in range(60)
    ]
    flagged = sum(v.fault_detected for v in verdicts)
    assert flagged <= stats.binom.ppf(1 - TEST_LEVEL, len(verdicts), ALPHA)


def test_a_magnitude_the_record_cannot_determine_within_the_range_is_not_given() -> None:
    """A near-spring mode trained over 0 … 1.5 % only: a record loosened by 1.5 % is found faulty
    by it, but its interval would span most of that range, so the verdict names the mode and
    gives no magnitude (the mode's σ̂_k stays in ``modes``)."""
    narrow = free_run_modes(("k2",), seed=97_000, magnitudes=(0.0, 0.5, 1.0, 1.5))
    span = narrow[0].model.basis.k_max - narrow[0].model.basis.k_min
    verdicts = [
        inspect_free_run(x, y, narrow, alpha=ALPHA) for _, x, y in faulty_records(3, 98_000, "k2", (1.5, 1.5))
    ]
    found = [v for v in verdicts if v.fault_detected]
    assert found
    assert all(v.status == "faulty" and v.fault_mode == "k2" for v in found)
    assert all(v.k_hat is None and v.sigma_k is None and v.interval is None for v in found)
    assert all(
        2 * stats.norm.ppf(1 - ALPHA / 2) * v.mode("k2").sigma_k > UNDETERMINED_SHARE * span for v in found
    )


def test_the_far_spring_is_given_no_magnitude_nor_a_sigma_k_a_perfect_model_could_not(modes) -> None:
    """The driving point barely feels the far spring (k3): its mode's interval spans most of its
    range on every record, and no verdict gives it a magnitude. Nor does the mode claim a σ̂_k
    below what a perfect model of the chain would reach (:func:`harness.noisy_modes.perfect_sigma_k`):
    a far spring's mode that took up the healthy point's misfit once claimed a slope hundreds of
    times the spring's and a σ̂_k as many times below that bound, a 12 % loosening sized near 0
    within a few hundredths (training set 52 000, since searched from a long ARX's fit as well:
    it no longer does, with or without σ̂_k scaled by the mode's misses of its own experiments).
    The near spring's σ̂_k is not scaled."""
    span = modes[1].model.basis.k_max - modes[1].model.basis.k_min
    verdicts = [
        inspect_free_run(x, y, modes, alpha=ALPHA)
        for _, x, y in faulty_records(4, 95_000, "k3", (13.0, 15.0))
    ]
    far = [v.mode("k3") for v in verdicts]
    assert all(mode.sigma_k >= perfect_sigma_k("k3", SAMPLES) / 2 for mode in far)
    assert all(2 * stats.norm.ppf(1 - ALPHA / 2) * mode.sigma_k > UNDETERMINED_SHARE * span for mode in far)
    assert not any(v.fault_mode == "k3" and v.interval is not None for v in verdicts)
    assert modes[0].scale == 1.0


def healthy_misfit_and_far_spring_change(mode: FreeRunMode) -> tuple[float, float]:
    """The RMS error of ``mode``'s healthy point running free on a noise-free healthy record, and
    the RMS change a 12 % loosening of the far spring makes to that record."""
    noise_free = replace(scenario(), y_noise_std=0.0, x_noise_std=0.0)
    x, y = record(noise_free, SAMPLES, 98_000)
    _, loosened = record(replace(noise_free, fault="k3", k=12.0), SAMPLES, 98_000)
    healthy = mode.model.narx_at(0.0)
    return float(np.std(estimated_start_error(healthy, x, y)[healthy.max_lag :])), float(np.std(loosened - y))


def test_the_healthy_point_simulates_the_chain_closer_than_the_far_spring_moves_it(modes) -> None:
    """The joint fit's healthy model runs free on a noise-free healthy record within a few times
    what a 12 % loosening of the far spring changes. From the equation-error start alone the
    search ended in another basin of the free-run error, a spurious negative pole in place of
    the slow one, several times further off: the far spring's mode then spent its slope on that
    misfit, not on the spring (its k̂ at the range's end on every record of some training sets,
    healthy ones too).

    Training set 61 000's searches both ended with a pole near −0.93 and a zero on it, the
    chain's response left to the ARX's three other poles: its healthy point missed a noise-free
    record by seven times what a 12 % looser far spring changes, and the far spring's mode
    claimed a slope of the wrong sign. Searched again with the pair taken out, the joint fit
    ends lower, with four slow poles and no such pair, within the bound the other training
    sets meet."""
    assert without_cancelled_poles(modes[0].model.narx_at(0.0)) is None
    misfit, change = healthy_misfit_and_far_spring_change(modes[0])
    assert misfit < 3 * change


def test_the_far_spring_trained_beyond_its_watched_range_follows_the_chain() -> None:
    """The far spring's slope is fixed by Σ(k − k̄)² times each experiment's information on k:
    from 0 … 15 % its error across the chain's change of the response was as large as that
    change (1.0 – 1.3 times it in three training sets, bench/noisy_modes.py designs), and the
    mode's k̂ shrank towards 0 under it. Trained at 0, 15, 30 and 45 % (nine times the
    information, the ARX's coefficients affine in one spring's stiffness), the mode changes a
    noise-free record from 0 to 12 % along the chain's change within a third of it and across it
    by less than 0.75 of it (0.35 – 0.47 in the same three)."""
    modes = free_run_modes(seed=63_000, magnitudes={"k2": MAGNITUDES, "k3": FAR_MAGNITUDES})
    along, across, _ = slope_against_truth(modes[1])
    assert abs(along - 1) < 1 / 3
    assert across < 0.75


def test_two_modes_the_record_cannot_tell_apart_give_an_unknown_fault(modes) -> None:
    """A mode and its twin under another name fit every record alike: the fault is detected, but
    which mode it is the record cannot say, so neither is named nor a magnitude given."""
    twin = replace(modes[0], model=replace(modes[0].model, name="k2 again"))
    x, y = record(scenario("k2", 9.0), SAMPLES, 96_000)
    alone = inspect_free_run(x, y, modes[:1], alpha=ALPHA)
    assert alone.status == "faulty" and alone.fault_mode == "k2"
    verdict = inspect_free_run(x, y, [modes[0], twin], alpha=ALPHA)
    assert verdict.fault_detected and verdict.status == "unknown_fault"
    assert verdict.fault_mode is None and verdict.interval is None
    assert all(mode.accepted for mode in verdict.modes)


def test_bad_requests_refused_with_a_message(modes) -> None:
    x, y = record(scenario(), SAMPLES, 1)
    with pytest.raises(InputError, match="at least one"):
        inspect_free_run(x, y, [])
    with pytest.raises(InputError, match="distinct"):
        inspect_free_run(x, y, [modes[0], modes[0]])
    with pytest.raises(InputError, match="alpha"):
        inspect_free_run(x, y, modes, alpha=0.7)
    with pytest.raises(InputError, match="samples"):
        inspect_free_run(x[:50], y[:50], modes)
    with pytest.raises(InputError, match="three magnitudes"):
        fit_free_run_modes({"k2": experiments("k2", 1)[:2]}, TERMS)


def test_a_mode_document_round_trips_and_a_damaged_one_is_refused(modes) -> None:
    x, y = record(scenario("k2", 8.0), SAMPLES, 3)
    again = [FreeRunMode.from_document(mode.to_document()) for mode in modes]
    assert inspect_free_run(x, y, again) == inspect_free_run(x, y, modes)
    document = modes[0].to_document()
    with pytest.raises(InputError, match="sigma2"):
        FreeRunMode.from_document({**document, "sigma2": -1.0})
    with pytest.raises(InputError, match="missing"):
        FreeRunMode.from_document({key: value for key, value in document.items() if key != "whitening"})
