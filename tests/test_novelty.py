"""Baseline-only monitoring (models/novelty.py): a structure that is not the rig, watched by the
simulation error of a baseline selected for it, with sensor noise on both measured signals."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import signal, stats

from harness.accelerometer import ALPHA, TERMS, record, scenario
from models.baseline_choice import MAX_ORDER, choose_baseline_terms
from models.errors import InputError
from models.narx import NARX, fit_narx
from models.novelty import NoveltyReference, judge_record, novelty_reference, start_up_of
from models.output_error import fit_output_error
from models.pooled import check_baseline
from models.terms import parse_terms
from simulator.chain import ChainScenario

TEST_LEVEL = 1e-3  # the chance a correct detector fails the rate assertions


@pytest.fixture(scope="module")
def baseline() -> tuple[NARX, NoveltyReference, list[tuple[np.ndarray, np.ndarray]]]:
    """The chain's ARX(8, 8) with no delay, as the API's tests train it: the choice of a
    baseline's terms is :func:`test_a_baseline_whose_terms_are_chosen_for_the_structure_holds_the_rate`'s.

    80 000 healthy samples, which the rates below need, in five records rather than ten: the
    reference's jackknife refits the baseline once a record on all the others, so five longer
    records cost it less than half of what ten would, for the same information."""
    healthy = scenario()
    training = [record(healthy, 16_000, 100 + i) for i in range(5)]
    model = fit_output_error(fit_narx(training, parse_terms(TERMS)), training, start_from="estimated").model
    return model, novelty_reference(model, training), training


def flagged(
    model: NARX, reference: NoveltyReference, s: ChainScenario, n: int, count: int, seed: int
) -> list:
    return [judge_record(model, reference, *record(s, n, seed + i), alpha=ALPHA) for i in range(count)]


def within_rate(verdicts: list) -> bool:
    """The number flagged within the binomial bounds of the designed rate (two-sided, at
    ``TEST_LEVEL``)."""
    count, anomalies = len(verdicts), sum(v.status == "anomaly" for v in verdicts)
    return (
        stats.binom.ppf(TEST_LEVEL, count, ALPHA)
        <= anomalies
        <= stats.binom.ppf(1 - TEST_LEVEL, count, ALPHA)
    )


def test_healthy_records_flagged_at_the_designed_rate_and_a_loosened_spring_found(baseline) -> None:
    model, reference, _ = baseline
    verdicts = flagged(model, reference, scenario(), 4000, 200, 10_000)
    assert within_rate(verdicts)
    assert all(v.free_run == "settled" for v in verdicts)
    severities = [v.severity for v in verdicts]
    assert abs(np.mean(severities) - 1.0) < 3 * np.std(severities) / np.sqrt(200)

    # Power for an 8 % loss of k1 or k2: the change the excitation explains stands far out of
    # the noise (bench/novelty_rates.py measures it); the bounds leave a few records' margin.
    for spring, least in (("k2", 38), ("k1", 38)):
        faulty = flagged(model, reference, scenario(spring, 8.0), 4000, 40, 20_000)
        assert sum(v.status == "anomaly" for v in faulty) >= least, spring
        assert np.median([v.severity for v in faulty]) > 1.0


def test_a_baseline_whose_terms_are_chosen_for_the_structure_holds_the_rate() -> None:
    """The terms a baseline trained without them gets (``choose_baseline_terms``: orders ≤ 6)
    from ten healthy records of 2000 samples: healthy records half as long are flagged within the
    binomial bounds of α, an 8 % loss of k2 at least 90 % of the time."""
    training = [record(scenario(), 2000, 100 + i) for i in range(10)]
    choice = choose_baseline_terms(training)
    assert choice.delay == 0 and choice.ny <= MAX_ORDER
    model = fit_output_error(fit_narx(training, list(choice.terms)), training, start_from="estimated").model
    reference = novelty_reference(model, training)
    assert within_rate(flagged(model, reference, scenario(), 1000, 200, 10_000))
    faulty = flagged(model, reference, scenario("k2", 8.0), 1000, 40, 20_000)
    assert sum(v.status == "anomaly" for v in faulty) >= 36


def test_the_rate_holds_at_half_and_twice_the_training_excitation(baseline) -> None:
    """The sensor noise is a floor and the baseline, fitted from the estimated start, has no
    bias that grows with the excitation: a healthy record's error spectrum is the same at any
    level. (From the first L measured outputs, the fit's bias flagged about half the records
    at twice the level.)"""
    model, reference, _ = baseline
    for level in (0.5, 2.0):
        verdicts = flagged(model, reference, scenario(level=level), 2000, 100, 40_000)
        assert within_rate(verdicts), level
        assert abs(np.mean([v.severity for v in verdicts]) - 1.0) < 0.02, level


def test_the_one_step_residual_flags_every_healthy_record_of_a_noisy_accelerometer(baseline) -> None:
    """Why the simulation error: the equation-error baseline check of the same structure, on the
    same records, finds nothing but the sensor noise its one-step residual amplifies."""
    _, _, training = baseline
    equation_error = fit_narx(
        training, parse_terms([f"y[t-{i}]" for i in range(1, 9)] + [f"x[t-{i}]" for i in range(8)])
    )
    healthy = scenario()
    flagged = [
        check_baseline(equation_error, *record(healthy, 4000, 30_000 + i)).fault_detected for i in range(10)
    ]
    assert sum(flagged) >= 9


def test_reference_document_round_trip(baseline) -> None:
    _, reference, _ = baseline
    assert NoveltyReference.from_document(reference.to_document()) == reference
    with pytest.raises(InputError, match="schema version"):
        NoveltyReference.from_document(reference.to_document() | {"schema_version": 99})


def test_a_version_3_document_is_judged_with_the_theory_covariance(baseline) -> None:
    """Deployed databases hold version-3 references, written before C was estimated: they mean
    C = I, the statistic gᵀ(G + G²)⁻¹g/(r·s²) they were designed with, and still judge."""
    model, reference, _ = baseline
    document = reference.to_document() | {"schema_version": 3}
    del document["covariance"]
    old = NoveltyReference.from_document(document)
    assert np.array_equal(old.covariance, np.eye(reference.rank))
    assert old == dataclasses.replace(reference, covariance=old.covariance)
    assert judge_record(model, old, *record(scenario(), 2000, 50_000)).status == "healthy"
    with pytest.raises(InputError, match="missing or invalid field"):
        NoveltyReference.from_document(document | {"schema_version": 4})
    with pytest.raises(InputError, match=f"covariance is not {reference.rank} × {reference.rank}"):
        NoveltyReference.from_document(reference.to_document() | {"covariance": [[1.0]]})


def first_order(a: float) -> NARX:
    """y[t] = a·y[t−1] + x[t−1]."""
    return NARX(parse_terms(["y[t-1]", "x[t-1]"]), np.array([a, 1.0]), np.zeros((2, 2)), 0.0, 0)


def simulated_by(model: NARX, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(n)
    return x, model.simulate(x, np.zeros(1)) + 0.05 * rng.standard_normal(n)


def coloured(model: NARX, colour: float, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A record of ``model`` whose response carries noise through the AR(1) filter 1/(1 − colour·q⁻¹):
    as coloured as the error that noise on the measured force leaves, G·n_x, in a slow structure."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(n)
    noise = signal.lfilter([1.0], [1.0, -colour], 0.1 * rng.standard_normal(n))
    return x, model.simulate(x, np.zeros(1)) + noise


def test_a_baseline_fitted_through_coloured_noise_holds_the_rate_by_its_jackknife() -> None:
    """Output error minimises the unwhitened error: through noise as coloured as a slow
    structure's, its θ is far less precise than the generalised least-squares σ²·I the
    statistic assumed (Gauss–Markov), and with C = I records as long as the training ones were
    flagged far above α, for the baseline's own error. The jackknife of the reference's refits
    sees it, and a 20 % slower pole is still found."""
    truth = first_order(0.5)
    training = [coloured(truth, 0.95, 500, 100 + i) for i in range(10)]
    model = fit_output_error(truth, training, start_from="estimated").model
    reference = novelty_reference(model, training)
    assert np.linalg.eigvalsh(reference.covariance)[-1] > 2.0
    healthy = [judge_record(model, reference, *coloured(truth, 0.95, 500, 10_000 + i)) for i in range(400)]
    assert within_rate(healthy)
    slower = first_order(0.6)
    faulty = [judge_record(model, reference, *coloured(slower, 0.95, 500, 20_000 + i)) for i in range(40)]
    assert sum(v.status == "anomaly" for v in faulty) >= 36


def test_a_baseline_that_diverges_on_its_own_records_is_refused() -> None:
    with pytest.raises(InputError, match="diverges on its healthy record 1"):
        novelty_reference(first_order(1.2), [simulated_by(first_order(0.5), 2000, 0)], folds=1)


def test_a_record_whose_free_run_diverges_is_an_anomaly_that_says_so() -> None:
    stable = first_order(0.5)
    reference = novelty_reference(stable, [simulated_by(stable, 2000, i) for i in range(3)], folds=1)
    assert judge_record(stable, reference, *simulated_by(stable, 2000, 9)).status == "healthy"
    verdict = judge_record(first_order(1.2), reference, *simulated_by(stable, 2000, 9))
    assert (verdict.status, verdict.free_run) == ("anomaly", "diverged")
    assert verdict.diverged_at is not None and verdict.diverged_at < 2000
    assert verdict.to_dict()["statistic"] is None


def test_a_baseline_nonlinear_in_its_output_is_refused() -> None:
    cubic = NARX(parse_terms(["y[t-1]", "y[t-1]^3", "x[t-1]"]), np.array([0.5, 0.05, 1.0]), np.zeros((3, 3)))
    with pytest.raises(InputError, match="linear in its output; y\\[t-1\\]\\^3"):
        novelty_reference(cubic, [simulated_by(first_order(0.5), 2000, 0)], folds=1)


def test_a_marginally_stable_baseline_is_judged_and_says_so() -> None:
    integrator = NARX(parse_terms(["y[t-1]", "x[t-1]"]), np.array([1.0, 0.01]), np.zeros((2, 2)), 0.0, 0)
    radius, start_up, marginal = start_up_of(integrator)
    assert (radius, start_up, marginal) == (1.0, 1, True)
    rng = np.random.default_rng(3)
    records = [
        (x, integrator.simulate(x, np.zeros(1)) + 0.01 * rng.standard_normal(1000))
        for x in rng.standard_normal((3, 1000))
    ]
    reference = novelty_reference(integrator, records, folds=1)
    verdict = judge_record(integrator, reference, *records[0])
    assert verdict.free_run == "marginal"
    assert np.isfinite(verdict.statistic)


def test_start_up_covers_the_ring_down_of_a_noisy_start() -> None:
    """A start error on y[t−1] of a first-order model 0.99 rings down as 0.99ᵗ: what is left after
    S, Σ_{s≥S} 0.99^{2s} = 0.99^{2S}/(1 − 0.99²), is below one hundredth."""
    model = NARX(parse_terms(["y[t-1]", "x[t-1]"]), np.array([0.99, 1.0]), np.zeros((2, 2)), 0.0, 0)
    _, start_up, marginal = start_up_of(model)
    left = lambda s: 0.99 ** (2 * s) / (1 - 0.99**2)  # noqa: E731
    assert not marginal and left(start_up) < 0.01 <= left(start_up - 1)
