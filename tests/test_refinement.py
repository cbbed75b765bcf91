"""The refinement loop: the missing effect is found, named, and the held-out error falls."""

from __future__ import annotations

import operator
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import replace
from functools import cache, partial

import numpy as np
import pytest
from scipy import linalg, signal, stats

from bench.measured import coupled_drives
from harness.duffing import DuffingOscillator
from harness.extrapolating import growing_steps
from harness.prerequisites import benchmark_data
from harness.warming import warming_drive
from models.checking import SETTLED_EVALUATIONS, CheckSplit, Structure, check_noise, split_for_checking
from models.effects import (
    HYSTERESIS,
    Effect,
    SearchInput,
    candidate_effects,
    linear_terms,
    offset_direction,
    offset_terms,
    polynomial_effect,
)
from models.errors import InputError
from models.growing import loop_on
from models.held_out import HeldOut, held_out_tails
from models.input_drive import feeds_through, input_drives
from models.linear_start import MAX_LINEAR_ORDER, _is_start
from models.narx import NARX, fit_narx
from models.output_error import RESTLESS, comes_to_rest, fit_output_error
from models.pruning import _ceiling, _first_removal, pruned_back, without_pruned
from models.refinement import (
    MAX_ROUNDS,
    Refinement,
    RefinementReport,
    Round,
    choose_linear,
    compare,
    refine,
    refine_record,
    refine_records,
)
from models.round_criteria import (
    DEFAULT_ALPHA,
    SIMULATION_GAIN,
    fitted_on_all,
    output_state_by_simulation,
    scored,
)
from models.scoring import EffectScore, Records, ScoringKept, fit_model, score_effects
from models.terms import Factor, Term, max_lag, parse_terms, regressor_matrix
from models.validation import validate
from recordfiles.reader import parse_silverbox
from simulator.simulate import Effects, Scenario, simulate
from simulator.theory import EXACT_TERMS

ESTIMATION, HELD_OUT = 8000, 4000
# Estimation records whose first ESTIMATION samples the loop runs on, the rest of them held out
# from its choices (models.held_out.HELD_OUT_SHARE).
LOOP_AND_TAIL = 10_000
# Official Silverbox split (shared/data/README.md); each test run starts from 50 measured outputs.
SILVERBOX_ESTIMATION = slice(40650, 105712)
SILVERBOX_ARROW = slice(100, 40575)
SILVERBOX_INITIAL = 50
NOISE = (np.random.default_rng(0).normal(size=3000), np.random.default_rng(1).normal(size=3000))


def paper_record(effects: list[str], seed: int, disturbance_std: float = 200.0):
    scenario = Scenario(disturbance_std=disturbance_std, effects=Effects.parse(effects))
    record = simulate(scenario, ESTIMATION + HELD_OUT, seed)
    return record.x, record.y


def process_effects(result: Refinement) -> tuple[str, ...]:
    """The effects the refined model holds in its process: all but the noise model chosen after
    the rounds (models.noise_model), which leaves the free run as it was."""
    return tuple(step.added.name for step in result.kept if step.added and step.criterion != "whiteness")


def held_out_errors(model, x, y, initial: int = 0):
    """Errors on a held-out stretch whose first ``initial`` samples only start the model."""
    start = max(initial - model.max_lag, 0)
    return validate(model, [(x[start:], y[start:])])


@pytest.fixture(scope="module")
def silverbox(silverbox_dir):
    return parse_silverbox((silverbox_dir / "SNLS80mV.csv").read_bytes())


# In `make slow`: bench/test_bench_refine.py's table test (`make bench`) runs the same loop on the
# same split through the command and asserts these four names as the first of its ten, and the
# final figures; `make test` keeps one Silverbox run, the command's on part of the estimation data
# (tests/test_cli_refine.py).
@pytest.mark.slow
def test_silverbox_from_linear_arx_finds_the_cubic_stiffness_and_the_offset(silverbox):
    """The loop's first four rounds (the whole loop, ten rounds, is bench/test_bench_refine.py's,
    through the command)."""
    x, y = silverbox.x, silverbox.y
    result = refine([(x[SILVERBOX_ESTIMATION], y[SILVERBOX_ESTIMATION])], linear_terms(4, 4), max_rounds=4)
    names = process_effects(result)
    assert names == ("missing_lags", "cubic_damping", "offset", "cubic_stiffness"), names
    test_x, test_y = x[SILVERBOX_ARROW], y[SILVERBOX_ARROW]
    before = held_out_errors(result.declared, test_x, test_y, SILVERBOX_INITIAL).free_run.rms
    after = held_out_errors(result.refined, test_x, test_y, SILVERBOX_INITIAL).free_run.rms
    # Linear ARX 14.39 mV (docs/benchmarks/measured.md); after four rounds 0.390 mV, with a
    # margin of about 10 % for
    # arithmetic differences between machines, not for a worse model.
    assert 13e-3 < before < 16e-3, f"linear ARX free run {before * 1e3:.2f} mV"
    assert after <= 0.43e-3, f"refined free run {after * 1e3:.3f} mV"


# One undeclared effect at a time, sized so that it, not the disturbance, dominates the declared
# model's residual; "quadratic_stiffness2" etc. act on the measured mass (simulator.simulate).
# The last figure bounds the held-out one-step RMS after refinement as a share of the one before:
# The docs' figure for the effect (seed 1 gives 0.008, 0.055, 0.211, 0.338, 0.270, 0.429) with a
# margin of about 20 % for arithmetic differences between machines (0.012 for Coulomb friction's
# 0.01, as the docs round it).
UNDECLARED = [
    ("coulomb_friction", Scenario(disturbance_std=200.0, effects=Effects(coulomb2=300.0)), 0.012),
    ("quadratic_damping", Scenario(disturbance_std=200.0, effects=Effects(quadratic_damping2=2e3)), 0.065),
    ("quadratic_stiffness", Scenario(disturbance_std=200.0, effects=Effects(quadratic_stiffness2=3e5)), 0.25),
    ("offset", Scenario(disturbance_std=200.0, effects=Effects(offset=0.02)), 0.40),
    (
        "periodic_disturbance",
        Scenario(disturbance_std=200.0, effects=Effects(sine_amplitude=1000.0, sine_frequency=12.5)),
        0.32,
    ),
    # Coloured force-sensor noise, the only noise: its moving average has |C|² = 5.95, so the best
    # one-step predictor's error is 1/√5.95 = 0.41 of the white-noise model's.
    ("moving_average_noise", Scenario(x_noise_std=800.0, noise_colour=(1.5, 1.2, 0.9, 0.6, 0.3)), 0.50),
]


@pytest.mark.parametrize(("effect", "scenario", "share"), UNDECLARED, ids=[name for name, *_ in UNDECLARED])
def test_an_undeclared_effect_is_named_first_and_the_one_step_error_falls(effect, scenario, share):
    record = simulate(scenario, ESTIMATION + HELD_OUT, seed=1)
    estimation, test = [(0, LOOP_AND_TAIL)], (LOOP_AND_TAIL, ESTIMATION + HELD_OUT)
    # The one-step criterion and least-squares parameters alone, as the loop first scored effects: its
    # figures are one-step errors, which output-error parameters do not minimise.
    report = refine_record(
        record.x, record.y, EXACT_TERMS, estimation, test, fs=record.fs, output_error=False
    )
    assert report.refinement.effects_added[0].name == effect, [
        e.name for e in report.refinement.effects_added
    ]
    assert report.after.one_step_rms <= share * report.before.one_step_rms, (report.before, report.after)


# The same effects where the free run is the figure of merit: an unmeasured force of 20 N, small
# beside the effect, so that the declared model's simulation error is the effect's. (Moving-
# average noise changes the predictions, not the simulation; an offset of y on the cubic spring
# is in one-step terms a quadratic stiffness at this noise level and is tested above.) Records
# half as long as those above: each effect dominates the declared model's free-run error so far
# that it is named first and the free run falls far below half of it; shorter still, the
# periodic disturbance's margin narrows.
SIMULATED_ESTIMATION, SIMULATED_HELD_OUT = 4000, 2000
SIMULATED = [
    ("coulomb_friction", Effects(coulomb2=300.0)),
    ("quadratic_damping", Effects(quadratic_damping2=2e3)),
    ("quadratic_stiffness", Effects(quadratic_stiffness2=3e5)),
    ("periodic_disturbance", Effects(sine_amplitude=1000.0, sine_frequency=12.5)),
]


@pytest.mark.parametrize(("effect", "effects"), SIMULATED, ids=[name for name, _ in SIMULATED])
def test_an_undeclared_effect_is_named_first_and_the_held_out_free_run_at_least_halves(effect, effects):
    samples = SIMULATED_ESTIMATION + SIMULATED_HELD_OUT
    record = simulate(Scenario(disturbance_std=20.0, effects=effects), samples, seed=1)
    estimation, test = [(0, SIMULATED_ESTIMATION)], (SIMULATED_ESTIMATION, samples)
    report = refine_record(record.x, record.y, EXACT_TERMS, estimation, test, fs=record.fs)
    assert report.refinement.effects_added[0].name == effect, [
        e.name for e in report.refinement.effects_added
    ]
    assert report.after.free_run_rms <= 0.5 * report.before.free_run_rms, (report.before, report.after)


def test_noise_first_in_the_one_step_order_gives_way_to_an_effect_that_simulates_better():
    """Every effect the process lacks colours the one-step residual, and moving-average noise,
    which models that colour, can rank first while its model runs free as the start does. On the
    rig with a cubic spring on the unmeasured mass, from linear:4,4, noise ranks far above the
    nonlinearity and clears by being no worse; the loop took it round after round. The round
    looks past it as past any first: the nonlinearity, which takes most of the check blocks' free
    run off, is named first (:func:`models.round_criteria.looked_ahead`)."""
    record = simulate(Scenario(disturbance_std=200.0, effects=Effects(cubic_stiffness1=4e6)), 1600, seed=1)
    start = linear_terms(4, 4)
    names = ("moving_average_noise", "unmeasured_nonlinearity")
    offered = [effect for effect in candidate_effects(start) if effect.name in names]
    result = refine([(record.x, record.y)], start, effects=offered, max_rounds=2)
    first = {score.name: score for score in result.rounds[0].scores}
    noise, nonlinearity = first["moving_average_noise"], first["unmeasured_nonlinearity"]
    assert noise.significant and nonlinearity.significant
    assert noise.bic_change < nonlinearity.bic_change, (noise.bic_change, nonlinearity.bic_change)
    # The premise, on the loop's own check blocks (the held-out tail left out): noise's model
    # runs free there as the start does, within the figure's standard error.
    split = held_out_tails([(record.x, record.y)])
    assert split is not None
    checks = CheckSplit.of(split[0])
    before = checks.error(Structure(tuple(start)))
    with_noise = checks.error(Structure(tuple(start), noise_lags=noise.noise_lags))
    assert abs(with_noise - before) < check_noise(checks.check) * before, (before, with_noise)
    step = result.rounds[0]
    assert step.added is not None and step.added.name == "unmeasured_nonlinearity", step.added
    assert step.check_rms[1] < 0.5 * step.check_rms[0], step.check_rms
    assert result.held_out is not None and result.held_out.kept


def test_the_periodic_disturbance_is_found_at_its_frequency():
    scenario = Scenario(disturbance_std=200.0, effects=Effects(sine_amplitude=1000.0, sine_frequency=12.5))
    record = simulate(scenario, ESTIMATION, seed=2)
    (first, *_) = refine([(record.x, record.y)], EXACT_TERMS).effects_added
    frequencies = {Term.parse(name).factors[0].frequency for name in first.terms}
    # The record is ~67 periods long: its frequency is resolved to a small part of 1/N.
    assert frequencies and all(abs(f * record.fs - 12.5) < 0.05 * record.fs / ESTIMATION for f in frequencies)


@pytest.mark.slow  # a Monte Carlo study of 20 loops: `make slow`
def test_on_clean_data_an_effect_is_added_to_few_records():
    """The issue's 100 records are bench/test_bench_refine.py's; here 20. Were effects added to 5 %
    of clean records, 4 or more of 20 would happen with probability 1.6 % (binomial): a loop
    that adds to one record in five fails this most of the time."""
    added = 0
    for seed in range(20):
        x, y = paper_record([], seed=1000 + seed, disturbance_std=800.0)
        added += bool(refine([(x[:ESTIMATION], y[:ESTIMATION])], EXACT_TERMS).effects_added)
    assert added <= 3, f"an effect was added to {added} of 20 clean records"


def test_nothing_is_added_to_unrelated_white_signals_whose_output_error_fit_is_restless():
    """Found in test_api_bounded: on x and y two unrelated white signals, the 2-DOF structure's
    output-error fit on the fit blocks did not come to rest, its check figure was infinite, and
    offset, power-law stiffness and Coulomb friction each passed the simulation criterion against
    it (a 20 % gain on infinity). A family decided on simulation must beat the current structure's
    best check figure, least squares' here. (Seed 117: on seeds 103 and 120, which showed it
    first, the search now ends at a fit that comes to rest, searched again where its end diverged
    from a measured state.)"""
    rng = np.random.default_rng(117)
    x, y = rng.normal(0.0, 1.0, 4000)[:2666], rng.normal(0.0, 1e-3, 4000)[:2666]
    checks = CheckSplit.of([(x, y)])
    declared = Structure(EXACT_TERMS)
    assert checks.error(declared, tuned=True) == np.inf and np.isfinite(checks.error(declared))
    result = refine([(x, y)], EXACT_TERMS)
    assert not [step.added.name for step in result.rounds if step.added is not None]


def _beside_own_past(
    declared: Sequence[Term], x: np.ndarray, y: np.ndarray, lag: int
) -> tuple[Callable[[np.ndarray], np.ndarray], np.ndarray, np.ndarray]:
    """An independent least-squares fit (SVD) for the one-step tests: the residual of the target
    on any columns, the declared regressors beside the residual's own last four values, and the
    target."""
    Phi, target = regressor_matrix(declared, x, y, lag)

    def residual_of(columns: np.ndarray) -> np.ndarray:
        scaled = columns / np.linalg.norm(columns, axis=0)
        return target - scaled @ linalg.lstsq(scaled, target, lapack_driver="gelsd")[0]

    residual = residual_of(Phi)
    own_past = np.column_stack([np.concatenate([np.zeros(k), residual[:-k]]) for k in range(1, 5)])
    return residual_of, np.hstack([Phi, own_past]), target


def test_score_and_f_statistic_agree_with_an_svd_refit():
    """An effect of the signals is credited with what it explains once the model and the
    residual's own last four values are in: both fits redone by SVD least squares (LAPACK
    gelsd, not the loop's Gram–Schmidt), and the F test from scipy.stats. (statsmodels' OLS
    is not used: its pseudo-inverse leaves relative errors ~5e-8 in these sums of squares, which
    the F statistic's difference of two of them magnifies ~100×.)"""
    x, y = paper_record(["quadratic_stiffness2=3e5"], seed=2)
    first = refine([(x[:LOOP_AND_TAIL], y[:LOOP_AND_TAIL])], EXACT_TERMS, max_rounds=1).rounds[0]
    x, y = x[:ESTIMATION], y[:ESTIMATION]  # what the loop saw, its tail held out
    assert first.added is not None and first.added.name == "quadratic_stiffness"
    declared = parse_terms(EXACT_TERMS)
    lag = max(max_lag(e.terms) for e in candidate_effects(declared) if e.terms)
    lag = max(lag, max_lag(declared))
    residual_of, base, target = _beside_own_past(declared, x, y, lag)
    extra, _ = regressor_matrix(parse_terms(first.added.terms), x, y, lag)
    restricted = np.sum(residual_of(base) ** 2)
    full = np.sum(residual_of(np.hstack([base, extra])) ** 2)
    assert first.added.explained == pytest.approx(1 - full / restricted, rel=1e-6)
    one_term = np.sum(residual_of(np.hstack([base, extra[:, :1]])) ** 2)
    dof = len(target) - base.shape[1] - 1
    f_value = (restricted - one_term) / (one_term / dof)
    assert first.added.f_statistics[0] == pytest.approx(f_value, rel=1e-6)
    assert first.added.p_values[0] == pytest.approx(stats.f.sf(f_value, 1, dof), rel=1e-5, abs=1e-300)
    assert first.level == pytest.approx(0.01 / first.candidates)


def test_a_searched_laws_first_block_counts_its_exponent_in_its_f_test():
    """A power law of y, its exponent searched beside the cubic spring's family, enters as a block
    of its lags (on the rig its first lag alone explains little of a contact's force), and the
    exponent, fitted to the same residual, is one more parameter of the block's joint F test:
    F = (RSS₀ − RSS₁)/(k + 1) over RSS₁/(N − p − k − 1), both fits redone by SVD least squares
    beside the residual's own last four values, the tail from scipy.stats."""
    record = simulate(Scenario(disturbance_std=200.0, effects=Effects(hertz_contact2=5e4)), 1600, seed=1)
    x, y = record.x, record.y
    declared = linear_terms(4, 4, 1)
    (law,) = [effect for effect in candidate_effects(declared) if effect.name == "power_law_stiffness"]
    assert law.integer_laws == (("cubic_stiffness", 3.0),)
    scores = score_effects([(x, y)], declared, 0, [law], DEFAULT_ALPHA)
    (score,) = scores.scores
    # The first block: the leading columns that share its F statistic; each after it alone.
    k = score.f_statistics.count(score.f_statistics[0])
    assert k > 1, score
    lag = max(max_lag(law_terms := parse_terms(score.terms[:k])), max_lag(declared))
    residual_of, base, target = _beside_own_past(declared, x, y, lag)
    extra, _ = regressor_matrix(law_terms, x, y, lag)
    restricted = np.sum(residual_of(base) ** 2)
    full = np.sum(residual_of(np.hstack([base, extra])) ** 2)
    dof = len(target) - base.shape[1] - k - 1
    f_value = (restricted - full) / (k + 1) / (full / dof)
    assert score.f_statistics[0] == pytest.approx(f_value, rel=1e-6)
    assert score.p_values[0] == pytest.approx(stats.f.sf(f_value, k + 1, dof), rel=1e-5, abs=1e-300)
    assert score.p_values[0] < scores.level


def test_candidate_effects_leave_out_terms_the_model_has():
    declared = parse_terms(["y[t-1]", "y[t-2]", "y[t-1]^3", "x[t-1]", "1"])
    effects = {effect.name: effect for effect in candidate_effects(declared)}
    assert "y[t-1]^3" not in [t.name for t in effects["cubic_stiffness"].terms]
    assert [t.name for t in effects["missing_lags"].terms] == ["y[t-3]", "y[t-4]", "x[t-2]", "x[t]"]
    # The constant is declared; an offset still brings the square its cubic term lowers to.
    assert [t.name for t in effects["offset"].terms] == ["y[t-1]^2"]
    linear_with_constant = parse_terms(["y[t-1]", "y[t-2]", "x[t-1]", "1"])
    assert "offset" not in {effect.name for effect in candidate_effects(linear_with_constant)}
    # Without the constant, a linear model is offered it first, then the cube it shows through.
    offset = {effect.name: effect for effect in candidate_effects(linear_with_constant[:-1])}["offset"]
    assert offset.kind == "combined" and offset.evidence_first
    assert [t.name for t in offset.terms] == ["1", "y[t-1]^2", "y[t-2]^2", "y[t-1]^3", "y[t-2]^3"]


def test_the_offset_a_linear_model_is_offered_is_the_cube_of_the_shifted_output():
    """On a linear model's residual that a cubic spring on the offset output leaves,
    w₁(y[t-1] − c)³ + w₂(y[t-2] − c)³, the offset family's one regressor is that function (its
    scale aside), where the cubes of y alone, fitted freely, leave a fifth of it unexplained."""
    x, y = paper_record([], seed=5)
    y = y + 0.5 * np.std(y)
    terms = linear_terms(2, 2)
    lag = 2
    Phi, _ = regressor_matrix(terms, x, y, lag)
    basis, _ = linalg.qr(Phi, mode="economic")

    def off_model(columns: np.ndarray) -> np.ndarray:
        return columns - basis @ (basis.T @ columns)

    c = 0.3 * np.std(y) + np.mean(y)
    lags, _ = regressor_matrix(parse_terms(["y[t-1]", "y[t-2]"]), x, y, lag)
    residual = off_model((lags - c) ** 3 @ np.array([1.0, -0.6]))
    (offset,) = [effect for effect in candidate_effects(terms) if effect.name == "offset"]
    assert offset.combine is not None
    spanning, regressor = offset.combine([(x, y)], residual, terms, lag)
    found = off_model(regressor)
    # c is searched to 10⁻³ of the output's range: what it leaves is of the order of that squared.
    assert 1 - np.corrcoef(found, residual)[0, 1] ** 2 < 1e-5
    cubes = off_model(lags**3)
    fit, *_ = linalg.lstsq(cubes, residual)
    assert np.sum((residual - cubes @ fit) ** 2) > 0.2 * np.sum(residual**2)
    assert [t.name for t in spanning] == ["1", "y[t-1]^2", "y[t-2]^2", "y[t-1]^3", "y[t-2]^3"]


def test_an_offset_that_shows_as_a_constant_is_the_constant():
    """A linear system with a static load, its model without a constant: the constant explains
    the residual itself, and the offset is that constant, not the cube it would show through."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=3000)
    noise = 0.01 * rng.normal(size=3000)
    y = signal.lfilter([0.0, 1.0], [1.0, -0.5, 0.2], x) + 0.3 / 0.7 + noise
    terms = linear_terms(2, 2)
    offered = [effect for effect in candidate_effects(terms) if effect.name == "offset"]
    (score,) = score_effects([(x, y)], terms, 0, offered, 0.01).scores
    assert score.significant and score.terms == ("1",), score


def test_a_sensor_offset_with_nothing_declared_is_named_first_with_the_rigs_spring():
    """The rig with an offset of 2 cm on its sensor, nothing declared (spent seed 8215, 4000
    samples): the linear start holds no constant, the one-step test sees none in its residual,
    and the rig's cubic spring, which reads (y − c)³, explains little as a cube of y. The loop
    used to name a slow sinusoid and damping laws as stand-ins, and the held-out tails returned the
    start, running free over another record at 47 times the rig-declared model's error. Offered
    with the cube it shows through, the offset is named first, and the model runs free as the
    rig-declared one does."""
    scenario = Scenario(disturbance_std=200.0, effects=Effects(offset=0.02))
    record, other = simulate(scenario, 4000, 8215), simulate(scenario, 4000, 8215 + 50_000)
    found = refine([(record.x, record.y)], None)
    rig = refine([(record.x, record.y)], EXACT_TERMS)
    assert found.effects_added[0].name == "offset", [e.name for e in found.effects_added]
    free_run = validate(found.refined, [(other.x, other.y)]).free_run.rms
    rig_free_run = validate(rig.refined, [(other.x, other.y)]).free_run.rms
    assert free_run <= 1.5 * rig_free_run, (free_run, rig_free_run)


def test_offset_direction_is_the_derivative_of_the_shifted_model():
    x, y = paper_record([], seed=5)
    terms = parse_terms(EXACT_TERMS)
    theta = np.random.default_rng(0).normal(size=len(terms)) * [1, 1, 1, 1, 10, 10, 10, 1e-10]
    lag = max_lag(terms)

    def shifted_prediction(c: float) -> np.ndarray:
        Phi, _ = regressor_matrix(terms, x, y - c, lag)
        return c + Phi @ theta

    step = 1e-6
    numerical = (shifted_prediction(step) - shifted_prediction(-step)) / (2 * step)
    np.testing.assert_allclose(offset_direction(terms, theta, x, y, lag), numerical, rtol=1e-6, atol=1e-9)
    assert [t.name for t in offset_terms(terms)] == ["1", "y[t-2]^2", "y[t-3]^2", "y[t-4]^2"]


def test_sensor_offset_is_named_first_and_the_one_step_error_halves():
    x, y = paper_record(["offset=0.02"], seed=6)
    result = refine([(x[:ESTIMATION], y[:ESTIMATION])], EXACT_TERMS)
    assert result.effects_added[0].name == "offset"
    before = held_out_errors(result.declared, x[ESTIMATION:], y[ESTIMATION:]).one_step.rms
    after = held_out_errors(result.refined, x[ESTIMATION:], y[ESTIMATION:]).one_step.rms
    assert after <= before / 2, (before, after)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: linear_terms(0, 2), "ny >= 1"),
        (lambda: linear_terms(2, 2, delay=-1), "delay >= 0"),
        (lambda: refine([(np.ones(100), np.ones(100))], ["y[t-1]"], alpha=1.5), "alpha"),
        (lambda: refine_record(*NOISE, EXACT_TERMS, [(0, 40)], (1000, 3000)), "estimation records have"),
        (lambda: refine_record(*NOISE, EXACT_TERMS, [(0, 2000)], (2000, 2004)), "test part has 4 samples"),
        (lambda: refine_record(*NOISE, EXACT_TERMS, [(0, 4000)], (0, 3000)), "estimation samples 0:4000"),
        (lambda: refine_record(*NOISE, EXACT_TERMS, [(0, 2000)], (2000, 3000), -1), "0 or more"),
    ],
)
def test_bad_arguments_are_refused_clearly(call, message):
    with pytest.raises(InputError, match=message):
        call()


def test_several_estimation_records_are_refined_at_once_and_judged_each():
    """Three records of one rig with Coulomb friction: the loop on all three names the friction,
    and each test record's free run at least halves. No lag reaches across records: the
    declared fit equals least squares on the three records' own equations stacked."""
    scenario = Scenario(disturbance_std=20.0, effects=Effects(coulomb2=300.0))
    records = [simulate(scenario, 4000, seed) for seed in (3, 4, 5)]
    tests = [simulate(scenario, 4000, seed) for seed in (6, 7)]
    report = refine_records([(r.x, r.y) for r in records], [(r.x, r.y) for r in tests], EXACT_TERMS)
    result = report.refinement
    assert result.effects_added[0].name == "coulomb_friction", [e.name for e in result.effects_added]
    assert len(report.tests) == 2
    for comparison in report.tests:
        assert comparison.after.free_run_rms <= 0.5 * comparison.before.free_run_rms
    declared = parse_terms(EXACT_TERMS)
    blocks = [regressor_matrix(declared, r.x, r.y) for r in records]
    Phi = np.vstack([b[0] for b in blocks])
    target = np.concatenate([b[1] for b in blocks])
    expected = linalg.lstsq(Phi, target, lapack_driver="gelsd")[0]
    assert result.declared.n_obs == target.size  # each record's own equations, none across
    # Agreement far inside the estimates' uncertainty (Φ is ill-conditioned: the two solvers
    # differ in the eighth digit).
    assert np.all(np.abs(result.declared.theta - expected) < 1e-2 * result.declared.standard_errors())
    assert any("not looked for" in note for note in report.notes)
    assert report.to_dict()["effects_added"][0]["decided_by"] in ("one-step", "simulation")


def test_with_nothing_declared_the_loop_chooses_the_linear_orders_of_the_system():
    """A linear third-order system measured with output noise: the orders chosen are (3, 3) with
    the input's one-sample delay, and the parameters are output-error ones (least squares is
    biased by the noise)."""
    rng = np.random.default_rng(8)
    n = 6000
    x = rng.standard_normal(n)
    clean = signal.lfilter(
        [0.0, 1.0, 0.5, 0.25], [1.0, -1.6, 1.06, -0.24], x
    )  # poles 0.43, 0.58 ± 0.46j (|0.75|)
    y = clean + 0.3 * np.std(clean) * rng.standard_normal(n)
    stages: list[str] = []
    result = refine([(x[:4000], y[:4000])], None, progress=stages.append)
    assert result.orders == (3, 3, 1), result.orders
    # Told each stage as it began: every linear candidate, then the rounds, then the final fit.
    candidates = [f"linear orders: ARX({n}, {n}), input delay {d}" for d in (1, 0) for n in range(1, 11)]
    assert stages[:20] == candidates
    # The orders chosen, judged with a constant: about zero it takes nothing off, and no more.
    assert stages[20] == "linear orders: ARX(3, 3) with a constant, input delay 1"
    assert stages[21] == f"round 1: scoring {len(candidate_effects(linear_terms(3, 3)))} families"
    assert stages[-1] == "output-error fit on all the records" and result.estimator == "output error"
    assert result.refined.max_lag >= 3
    free_run = result.refined.simulate(x[4000:], clean[4000:])[3:] - clean[4003:]
    least_squares = result.declared.simulate(x[4000:], clean[4000:])[3:] - clean[4003:]
    assert np.sqrt(np.mean(free_run**2)) < np.sqrt(np.mean(least_squares**2))


def test_the_check_split_fits_a_structure_once_and_searches_from_that_fit():
    """Each round asks for the current structure's check figure again, and the output-error
    search after the rounds starts from the least-squares fit the judgement made: on Silverbox
    that fit (extended least squares, 30 steps over 43 000 rows) was made twice."""
    x, y = paper_record(["cubic_stiffness1=4e6"], seed=4)
    checks = CheckSplit.of([(x[:ESTIMATION], y[:ESTIMATION])])
    structure = Structure(tuple(parse_terms(EXACT_TERMS)), noise_lags=2)
    least_squares = checks.fitted(structure)
    assert np.isfinite(checks.error(structure))
    assert checks.fitted(structure) is least_squares
    refit = CheckSplit.of([(x[:ESTIMATION], y[:ESTIMATION])]).fitted(structure)
    assert np.array_equal(refit.theta, least_squares.theta)  # the kept fit is the fit
    tuned = checks.tuned(structure)
    assert checks.fitted(structure) is least_squares and tuned.terms == least_squares.terms


def test_a_grown_structure_that_cannot_be_fitted_is_searched_to_an_infinite_figure():
    """A grown structure least squares cannot fit (here one listing a term twice, as the loop once
    grew one) is searched from least squares, which raises: its figure is infinite, as
    CheckSplit.error judges it, and kept, so that search_grown, which reads the kept figures,
    yields it rather than failing on a figure never kept."""
    rng = np.random.default_rng(3)
    x = rng.standard_normal(1800)
    y = signal.lfilter([0.0, 1.0], [1.0, -1.5, 0.7], x)
    current = Structure(tuple(parse_terms(["y[t-1]", "y[t-2]", "x[t-1]"])))
    cube = parse_terms(["y[t-1]^3"])
    twice, grown = Structure(current.terms + cube + cube), Structure(current.terms + cube)
    checks = CheckSplit.of([(x, y)])
    with pytest.raises(InputError, match="listed twice"):
        checks.fitted(twice)
    assert checks.error(twice, tuned=True) == np.inf

    searched = CheckSplit.of([(x, y)])
    figures = list(searched.search_grown(current, [twice, grown], 10))

    assert figures[0] == np.inf and searched.error(twice, tuned=True) == np.inf
    assert np.isfinite(figures[1]) and figures[1] == searched.error(grown, tuned=True)


def test_structures_judged_in_processes_are_judged_as_in_this_one():
    """A round's families are judged side by side in worker processes (CheckSplit.judge): the
    figures, and the fits kept for the searches after, are those this process makes, and the
    judgements come back in the order asked, each structure judged once; so are the first fold's
    searches across folds (CheckSplit.search_grown)."""
    x, y = paper_record(["cubic_stiffness1=4e6"], seed=4)
    records = [(x[:ESTIMATION], y[:ESTIMATION])]
    exact = tuple(parse_terms(EXACT_TERMS))
    structures = [
        Structure(exact[:4]),
        Structure(exact, noise_lags=2),  # extended least squares
        Structure(exact),
        Structure(exact[:4]),  # asked again: judged once
    ]
    here = CheckSplit.of(records)
    expected = [here.error(structure) for structure in structures]
    tuned = here.error(structures[0], tuned=True)
    # The searches across folds: each grown structure from the current one's output-error fit.
    grown = [Structure(exact[:4] + exact[4:5]), Structure(exact[:4] + exact[5:6])]
    searched = [here.search(structure, here.grown(structures[0], structure), 10) for structure in grown]
    there = CheckSplit.of(records)
    with ProcessPoolExecutor(2) as pool:
        assert list(there.judge(structures, pool.map)) == expected
        assert list(there.judge(structures[:1], pool.map, tuned=True)) == [tuned]
        assert list(there.search_grown(structures[0], grown, 10, pool.map)) == searched
    assert len(set(expected)) == 3 and all(np.isfinite(expected))
    assert set(there._fitted) == set(structures + grown) and set(there._tuned) == {
        structures[0],
        *grown,
    }  # kept
    for structure in structures + grown:
        assert np.array_equal(there.fitted(structure).theta, here.fitted(structure).theta)
    for structure in [structures[0], *grown]:
        assert np.array_equal(there.tuned(structure).theta, here.tuned(structure).theta)
    assert searched[0] != searched[1] and all(np.isfinite(searched))


def test_linear_orders_chosen_in_processes_are_chosen_as_in_this_one():
    """With nothing declared, the linear candidates are judged side by side in worker processes
    (``narxwatch refine --jobs``): the same orders and terms as judged here (on the record of the
    rig with nothing planted below, judged here once for both tests)."""
    records, here = planted_and_chosen("none", 1)
    with ProcessPoolExecutor(2) as pool:
        assert choose_linear(records, workers=pool.map) == here


def test_a_judgement_by_output_error_searches_from_the_fit_kept_here():
    """A structure judged with its output-error fit in a split of its own (a worker's) is
    searched from the least-squares fit this split kept, not from one the worker makes again:
    given another start, it ends elsewhere."""
    x, y = paper_record(["cubic_stiffness1=4e6"], seed=4)
    records = [(x[:ESTIMATION], y[:ESTIMATION])]
    structure = Structure(tuple(parse_terms(EXACT_TERMS))[:4])
    here = CheckSplit.of(records)
    fitted = here.fitted(structure)
    (expected,) = here.judge([structure], map, tuned=True)
    moved = CheckSplit.of(records)
    moved._fitted[structure] = replace(fitted, theta=fitted.theta * (1 + 1e-6))
    (judged,) = moved.judge([structure], map, tuned=True)
    assert np.isfinite(judged) and judged != expected
    assert not np.array_equal(moved.tuned(structure).theta, here.tuned(structure).theta)


@pytest.mark.parametrize("rank", [False, True])
def test_families_tested_in_threads_score_as_in_one(rank: bool):
    """Each round's families are tested in threads of the loop's process (score_effects'
    ``threads``): every score, to the last digit and in the order offered, is the one a single
    thread gives, with moving-average terms in the model and its noise family tested after."""
    x, y = paper_record(["cubic_stiffness1=4e6"], seed=4)
    records = [(x[:ESTIMATION], y[:ESTIMATION])]
    terms = tuple(parse_terms(EXACT_TERMS))[:4]
    effects = candidate_effects(terms)
    alone = score_effects(records, terms, 1, effects, 0.01, rank=rank)
    with ThreadPoolExecutor(2) as pool:
        threaded = score_effects(records, terms, 1, effects, 0.01, rank=rank, threads=pool.map)
    assert threaded == alone
    assert [score.name for score in threaded.scores] == [effect.name for effect in effects]
    assert sum(score.significant for score in alone.scores) >= 2


def test_from_three_records_on_whole_records_are_checked():
    """A sine sweep's blocks hold different frequencies, so a block split judges a model at
    frequencies its fit never saw (F-16: orders (2, 2) chosen). Records alike in design are
    checked whole instead: every third from the second, the others fitted whole."""
    records = [(np.full(300, float(i)), np.full(300, float(i))) for i in range(7)]
    fit, check = split_for_checking(records)
    assert [x[0] for x, _, _ in check] == [1.0, 4.0]
    assert [x[0] for x, _, _ in fit] == [0.0, 2.0, 3.0, 5.0, 6.0]
    assert all(len(y) == 300 and t0 == 0 for _, y, t0 in fit + check)
    one_fit, one_check = split_for_checking(records[:1])
    assert len(one_fit) == len(one_check) == 1 and one_check[0][2] == 200  # 300 // 3 = 1 block


def test_the_three_folds_check_every_record_once_and_never_fit_the_records_they_check():
    """The simulation criterion across folds (step 5) rotates which third of the records is
    checked: over the three folds each record is checked exactly once, and no fold fits a record
    it checks."""
    records = [(np.full(300, float(i)), np.full(300, float(i))) for i in range(7)]
    checked = []
    for fold in (0, 1, 2):
        fit, check = split_for_checking(records, fold)
        fitted = {x[0] for x, _, _ in fit}
        assert fitted.isdisjoint(x[0] for x, _, _ in check)
        assert len(fitted) + len(check) == len(records)
        checked += [x[0] for x, _, _ in check]
    assert sorted(checked) == [float(i) for i in range(7)]


def test_the_refined_model_simulates_the_estimation_data_no_worse_than_the_declared_output_error_fit():
    """Its output-error search starts from the better of its least-squares fit and the declared
    model's output-error fit grown by the added terms at zero, so it cannot end worse than the
    latter (on the F-16 sweeps the search from least squares did: 0.184 against 0.156 m/s² on level
    2 for acceleration 1, bench/measured.py). (Seed 11 ended on least squares once the simulation
    criterion stopped passing families against an infinite figure: 13 ends on output error.)"""
    rng = np.random.default_rng(13)
    n = 6000
    x = rng.standard_normal(n)
    clean = signal.lfilter([0.0, 0.4, 0.2], [1.0, -1.5, 0.7], x)
    y = clean + 0.05 * clean**3 + 0.5 * np.std(clean) * rng.standard_normal(n)
    declared = linear_terms(2, 2)
    result = refine([(x, y)], declared)
    assert result.estimator == "output error"
    least_squares_fit = fit_narx([(x, y)], declared)
    declared_tuned = fit_output_error(least_squares_fit, [(x, y)], SETTLED_EVALUATIONS).model

    def free_run_rms(model):
        return np.sqrt(np.mean((model.simulate(x, y)[2:] - y[2:]) ** 2))

    assert free_run_rms(result.refined) <= free_run_rms(declared_tuned) * (1 + 1e-9)


@pytest.fixture(scope="module")
def measurement_noise_only():
    """The rig with SPEC §2's structure declared and 2 µm of white noise on the measured output:
    nothing is missing from the structure, but least squares is biased by the noise, and in this
    record the loop used to add an effect (power-law damping) that lowered the check blocks' free
    run by 0.08 %, far within its 1.4 % standard error."""
    record = simulate(Scenario(disturbance_std=200.0, y_noise_std=2e-6), ESTIMATION + HELD_OUT, seed=2005)
    # The loop runs on the first 8000 samples, the rest held out from its choices (refine).
    estimation = [(record.x[:LOOP_AND_TAIL], record.y[:LOOP_AND_TAIL])]
    return record, estimation, refine(estimation, EXACT_TERMS)


def test_an_effect_decided_on_one_step_lowers_the_check_free_run_by_more_than_its_noise(
    measurement_noise_only,
):
    _, estimation, result = measurement_noise_only
    margin = check_noise(split_for_checking(estimation)[1])
    for step in result.rounds:
        if step.criterion == "one-step" and step.added.noise_lags == 0:
            before, after = step.check_rms
            assert after < (1 - margin) * before, (step.added.name, before, after, margin)


def test_effects_that_only_repair_the_bias_of_least_squares_are_withdrawn(measurement_noise_only):
    """With output-error parameters the declared structure simulates the check blocks better than
    the grown one: the effects (missing lags, moving-average noise) only stood in for the noise's
    bias. Past the initial transient the withdrawn model simulates the held-out data better than
    the grown structure does with output-error parameters of its own, both coming to rest.

    The transient is what a free run started from four outputs measured with noise gets wrong
    about the rig's slow mode, for two thousand samples here (16 mm RMS in the true model's own
    free run, 0.7 mm after): started on the held-out record itself, the model with more lags
    wins by reading its state better (3.5 mm against 9.3 mm). So the free run starts a thousand
    samples earlier, and only the held-out samples are judged."""
    record, estimation, result = measurement_noise_only
    assert result.withdrawn and result.effects_withdrawn and not process_effects(result)
    # Noise on the measured output colours the equation error: the noise model, after the rounds.
    assert {effect.name for effect in result.effects_added} == {"moving_average_noise"}
    assert result.refined.terms == parse_terms(EXACT_TERMS)
    assert result.estimator == "output error"
    grown_terms = parse_terms(EXACT_TERMS) + tuple(
        term
        for step in result.rounds
        if step.added and not step.added.noise_lags
        for term in parse_terms(step.added.terms)
    )
    grown = fit_output_error(fit_narx(estimation, grown_terms), estimation, SETTLED_EVALUATIONS).model
    assert comes_to_rest(grown, estimation) and comes_to_rest(result.refined, estimation)
    warm_up = 1000
    x, y = record.x[LOOP_AND_TAIL - warm_up :], record.y[LOOP_AND_TAIL - warm_up :]

    def held_out_rms(model: NARX) -> float:
        error = model.simulate(x, y)[warm_up:] - y[warm_up:]
        return float(np.sqrt(np.mean(error**2)))

    assert held_out_rms(result.refined) < held_out_rms(grown)


def test_a_model_to_which_nothing_is_added_is_the_declared_structures_output_error_fit(
    measurement_noise_only,
):
    """Not a second search from other starts, which ends at another optimum of the same structure,
    better or worse on other records by chance (F-16's acceleration 2 from the chosen linear
    orders: 5–7 % worse than the best linear model on two test levels, bench/measured.py, which
    computes that model as this test does)."""
    _, estimation, result = measurement_noise_only
    assert not process_effects(result) and result.refined.terms == parse_terms(EXACT_TERMS)
    declared = fit_output_error(fit_narx(estimation, EXACT_TERMS), estimation, SETTLED_EVALUATIONS).model
    np.testing.assert_array_equal(result.refined.theta, declared.theta)


def hardening_mode(cubic: float, level: float, seed: int, n: int = 3000):
    """A lightly damped mode (poles 0.95·e^±0.2j) with a hardening spring, y[t] = 1.862 y[t-1]
    − 0.9025 y[t-2] + 0.01 x[t-1] − ``cubic``·y[t-1]³, driven by low-passed noise of RMS ∝
    ``level`` and measured with white noise of 30 % of its RMS. Returns x, the measured y and the
    noise-free y."""
    rng = np.random.default_rng(seed)
    x = level * signal.lfilter([1.0], [1.0, -0.9], rng.standard_normal(n))
    a1, a2 = 2 * 0.95 * np.cos(0.2), -(0.95**2)
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = a1 * y[t - 1] + a2 * y[t - 2] + 0.01 * x[t - 1] - cubic * y[t - 1] ** 3
    return x, y + 0.3 * np.std(y) * rng.standard_normal(n), y


@cache
def across_folds(
    cubic: float, shift: float, offered: tuple[str, ...]
) -> tuple[Records, Refinement, tuple[str, ...]]:
    """The mode at three levels, as F-16's sweeps (levels 1, 1.5 and 2, seeds 1 to 3), its readings
    shifted by ``shift``, refined from linear:2,2 with the ``offered`` families alone; the stages
    told. Made once a process: two tests read the spring's loop with its one family."""
    records = [hardening_mode(cubic, level, seed) for level, seed in ((1.0, 1), (1.5, 2), (2.0, 3))]
    estimation = [(x, y + shift) for x, y, _ in records]
    declared = linear_terms(2, 2)
    families = [effect for effect in candidate_effects(declared) if effect.name in offered]
    stages: list[str] = []
    result = refine(estimation, declared, effects=families, progress=stages.append)
    return estimation, result, tuple(stages)


@pytest.mark.parametrize("cubic", [0.0, 0.01])
def test_from_three_records_a_family_that_every_fold_simulates_better_is_added_across_folds(cubic):
    """Three records of the mode at three levels, as F-16's sweeps: least squares, biased by the
    output noise, fits a cubic stiffness that runs free no better over the check record, so the
    one-step criterion rejects it and the simulation criterion finds it below its 20 %. Grown at
    zero from the settled linear output-error fit, it lowers every fold's free run by more than
    ``FOLD_GAIN`` and is added across folds; on a record at another level the refined model's
    free run is at most half as far from the noise-free output as the linear structure's settled
    output-error fit, both started from noise-free outputs (0.010 against 0.22). Without the
    spring nothing is added (none in five seeds tried; the spring in
    five of five)."""
    estimation, result, stages = across_folds(cubic, 0.0, ("cubic_stiffness",))
    declared = linear_terms(2, 2)
    decided = [step.criterion for step in result.rounds if step.added is not None]
    assert stages[0] == "round 1: scoring 1 family"
    if cubic == 0.0:
        assert decided == [], decided
        return
    assert "cubic_stiffness" in result.rounds[0].rejected
    assert decided == ["simulation across folds"], decided
    order = [
        stages.index(stage)
        for stage in (
            "round 1: cubic_stiffness on the check blocks",
            "round 1: the families on the simulation error",
            "across folds: cubic_stiffness on the first fold",
            "across folds: cubic_stiffness on every fold",
            "output-error fit on all the records",
        )
    ]
    assert order == sorted(order), stages
    assert all(term.endswith("^3") for term in result.effects_added[0].terms)
    x, _, clean = hardening_mode(cubic, 1.75, 9)
    linear = fit_output_error(fit_narx(estimation, declared), estimation, SETTLED_EVALUATIONS).model

    def from_clean(model: NARX) -> float:
        return float(np.sqrt(np.mean((model.simulate(x, clean)[2:] - clean[2:]) ** 2)))

    assert from_clean(result.refined) <= 0.5 * from_clean(linear), (
        from_clean(result.refined),
        from_clean(linear),
    )


@pytest.mark.parametrize(
    ("shift", "offered", "decided"),
    [
        (0.0, ("cubic_stiffness",), ["simulation across folds"]),
        # The sensor's offset, added by the rounds and kept, then the spring across folds and
        # the offset of its cubes: the procedure starts from the kept structure's settled fit.
        (
            0.5,
            ("cubic_stiffness", "offset"),
            ["one-step", "simulation across folds", "simulation across folds"],
        ),
    ],
)
def test_a_family_added_across_folds_is_fitted_on_all_the_records_as_the_folds_fitted_it(
    shift, offered, decided
):
    """The folds judge a procedure — the family's terms grown at zero from the settled fit of the
    structure before it, searched until they stop gaining — so the refined model is that procedure
    on all the records, computed here independently. The loop used to search from whichever start
    simulated best, the first fold's fit among them: on F-16's acceleration 3 that ended 0.7 %
    lower on the estimation records and 60 % higher on the test sweep below their levels."""
    estimation, result, _ = across_folds(0.01, shift, offered)
    declared = linear_terms(2, 2)
    added = [step for step in result.rounds if step.added]
    assert [step.criterion for step in added] == decided
    assert result.estimator == "output error"

    def settled(model: NARX) -> NARX:
        return fit_output_error(model, estimation, SETTLED_EVALUATIONS).model

    terms = declared
    for step in added:
        if step.criterion == "one-step":
            terms += parse_terms(step.added.terms)
    model = settled(fit_narx(estimation, terms))
    for step in added[len(added) - decided.count("simulation across folds") :]:
        grown = fit_narx(estimation, terms := terms + parse_terms(step.added.terms))
        fitted = dict(zip(model.terms, model.theta, strict=True))
        model = settled(replace(grown, theta=np.array([fitted.get(term, 0.0) for term in grown.terms])))
    assert result.refined.terms == terms
    np.testing.assert_allclose(result.refined.theta, model.theta, rtol=1e-9, atol=1e-12)


def test_from_three_records_effects_that_do_not_simulate_better_on_every_fold_are_withdrawn():
    """The mode without its spring, every family on offer: the one-step criterion adds
    power-law damping (of exponent near one: two more linear lags) and moving-average noise on
    the first fold's check record, but settled by output error the grown structure does not
    simulate better than the declared one on every fold, and both are withdrawn; nothing is added
    across folds, and the refined model is the declared (true) structure's output-error fit."""
    records = [hardening_mode(0.0, level, seed) for level, seed in ((1.0, 1), (1.5, 2), (2.0, 3))]
    estimation = [(x, y) for x, y, _ in records]
    declared = linear_terms(2, 2)
    result = refine(estimation, declared)
    assert result.effects_withdrawn and not process_effects(result), (
        result.effects_withdrawn,
        result.effects_added,
    )
    assert result.refined.terms == declared and result.estimator == "output error"
    # Each effect named once, however many rounds added it (moving-average noise took two here).
    names = [step.added.name for step in result.rounds[: result.withdrawn] if step.added is not None]
    assert sorted(result.effects_withdrawn) == sorted(set(names)), (result.effects_withdrawn, names)


# The 2-DOF rig observed at mass 2 is of fourth order (SPEC §2's structure: y[t-1…t-4]); a
# planted nonlinearity the start lacks must not move the linear orders chosen with nothing
# declared (a dead zone of 10 kN chose ARX(3, 3), or ARX(2, 2) extrapolating y's own past).
PLANTED = [
    ("none", 1),
    ("dead_zone=10000", 1),
    ("dead_zone=10000", 2),
    ("dead_zone=5000", 3),
    ("backlash=3000", 2),
    ("quadratic_damping2=2000", 3),
]


@cache
def planted_and_chosen(effect: str, seed: int) -> tuple[Records, tuple]:
    """The loop's head of a 2400-sample record of the rig with ``effect`` planted (800 N of
    unmeasured force), and the linear orders and terms chosen on it with nothing declared."""
    effects = Effects.parse([effect]) if effect != "none" else Effects()
    record = simulate(Scenario(disturbance_std=800.0, effects=effects), 2400, seed)
    records = [(record.x[:1600], record.y[:1600])]
    return records, choose_linear(records)


@pytest.mark.parametrize(("effect", "seed"), PLANTED)
def test_with_nothing_declared_a_planted_effect_leaves_the_start_at_the_rigs_order(effect, seed):
    _, (orders, _) = planted_and_chosen(effect, seed)
    assert orders == (4, 4, 1), orders


# Effects under which every linear model runs free poorly, as the planted benchmark plants them
# (200 N of unmeasured force, the loop's head of a 1600-sample record): ARX(2, 2), whose input
# lags stop short of the rig's x[t-4], ran free as well as ARX(4, 4) and was the start. On seed 3
# every order the input drives diverged on one rotation but ARX(9, 9), whose free run stayed
# finite there at twice the output's spread and reached a hundred times it on another, and it
# was the start.
POORLY_SIMULATED = [
    ("quadratic_stiffness2=3e5", 1),
    ("sensor_range=0.08", 2),
    ("quadratic_stiffness2=3e5", 3),
]


@pytest.mark.parametrize(("effect", "seed"), POORLY_SIMULATED)
def test_with_nothing_declared_a_start_the_input_does_not_drive_gives_way_to_the_rigs_order(effect, seed):
    record = simulate(Scenario(disturbance_std=200.0, effects=Effects.parse([effect])), 1600, seed)
    orders, _ = choose_linear([(record.x[:1280], record.y[:1280])])
    assert orders == (4, 4, 1), orders


def test_with_the_sensor_clipping_the_orders_are_judged_as_a_clipping_sensors_models():
    """The rig read through a sensor clipping at ±0.08 m (200 N of unmeasured force, the loop's
    head of a 1600-sample record, a quarter of it clipped). Judged as plain linear models, which
    run free from clipped readings and are scored unclipped against them, every order ran free
    over the rotations at about 0.05 m, ARX(6, 6) a little lower, and it was the start; the loop
    named the saturation, found no room for the rig's cubic spring beside the higher order, and
    its model ran free over another record ten times as far off as the rig's. Judged as a
    clipping sensor's models, fitted and run clear of the plateaus, ARX(4, 4) runs free far
    closer and no higher order better."""
    record = simulate(
        Scenario(disturbance_std=200.0, effects=Effects.parse(["sensor_range=0.08"])), 1600, 8213
    )
    orders, _ = choose_linear([(record.x[:1280], record.y[:1280])])
    assert orders == (4, 4, 1), orders


def test_a_start_the_input_does_not_drive_is_not_taken_for_running_free_better():
    """On 3200 samples of the rig whose sensor clips nearly half of them (the loop's head of a
    4000-sample record), every linear model driven through the clipping runs free poorly, and
    ARX(2, 2), whose input lags stop short of the rig's x[t-4], extrapolates the output's past
    better than ARX(4, 4) on all three rotations. It was the start, and the loop, its families
    sized to x[t-1…t-2], named moving-average noise; from ARX(4, 4) it names the saturation."""
    clipped = simulate(Scenario(disturbance_std=200.0, effects=Effects.parse(["sensor_range=0.08"])), 4000, 2)
    records = [(clipped.x[:3200], clipped.y[:3200])]
    level = DEFAULT_ALPHA / (4 * MAX_LINEAR_ORDER)
    assert not input_drives(records, linear_terms(2, 2, 1), level)
    orders, _ = choose_linear(records)
    assert orders == (4, 4, 1), orders


def test_the_input_drives_the_rigs_order_and_not_the_orders_short_of_its_delay():
    """The rig's input reaches y at x[t-4] alone (SPEC §2): a white input at x[t-1…t-3] has not
    reached the output yet and is independent of it, so an ARX whose input lags stop there has
    no input coefficient to find, whatever an effect does to the equation error. With the sensor
    clipping, the equations on and around its plateaus do not follow the input at all; left out,
    ARX(4, 4)'s x[t-4] is found."""
    # The level choose_linear tests each of its forty candidates at, the loop's over their number.
    level = DEFAULT_ALPHA / (4 * MAX_LINEAR_ORDER)
    for effect, seed in [("quadratic_stiffness2=3e5", 1), ("sensor_range=0.08", 2), ("none", 3)]:
        effects = Effects.parse([effect]) if effect != "none" else Effects()
        record = simulate(Scenario(disturbance_std=200.0, effects=effects), 1280, seed)
        records = [(record.x, record.y)]
        assert input_drives(records, linear_terms(4, 4, 1), level), effect
        for n, d in [(1, 1), (2, 1), (3, 1), (2, 0), (4, 0)]:
            assert not input_drives(records, linear_terms(n, n, d), level), (effect, n, d)
    clipped = simulate(Scenario(disturbance_std=200.0, effects=Effects.parse(["sensor_range=0.08"])), 1280, 2)
    # The plateaus left in, the input's effect is lost in their equations.
    unlimited = [(clipped.x, clipped.y + 1e-12 * np.arange(clipped.y.size))]
    assert not input_drives(unlimited, linear_terms(4, 4, 1), level)


def test_a_candidate_that_does_not_simulate_a_rotation_is_not_near_the_best():
    """The rig with power-law damping, the loop's head of a 2000-sample record: ARX(7, 7) ran free
    over two rotations as well as the best and over the third at sixty times the output's spread
    about its mean. That rotation widened the spread of its difference from the best, which then
    passed it as near the best, and as the smallest so near it was the start. A candidate that
    has not simulated a rotation the best simulated is not near it."""
    effects = Effects.parse(["power_damping2=1000"])
    record = simulate(Scenario(disturbance_std=200.0, effects=effects), 2000, 2)
    orders, _ = choose_linear([(record.x[:1600], record.y[:1600])])
    assert orders == (4, 4, 1), orders


def test_a_delay_of_0_is_chosen_only_where_the_input_at_the_same_sample_is_significant():
    """The rig's force reaches the measured output at x[t-4] (SPEC §2), so x[t] is independent of
    it. With coloured noise on the force sensor (the planted benchmark's moving-average noise,
    the loop's head of a 1600-sample record) ARX(5, 5) with x[t] ran free over the three
    rotations a little better than ARX(4, 4), its x[t] coefficient nil (p = 0.4), and was the
    start. A system whose output feels the input at once keeps its x[t]."""
    level = DEFAULT_ALPHA / (4 * MAX_LINEAR_ORDER)
    scenario = Scenario(x_noise_std=800.0, noise_colour=(1.5, 1.2, 0.9, 0.6, 0.3))
    record = simulate(scenario, 1600, 4)
    records = [(record.x[:1280], record.y[:1280])]
    assert input_drives(records, linear_terms(5, 5, 0), level)
    assert not feeds_through(records, linear_terms(5, 5, 0), level)
    orders, _ = choose_linear(records)
    assert orders == (4, 4, 1), orders
    rng = np.random.default_rng(3)
    x = rng.standard_normal(1280)
    # An accelerometer under the force: the output's numerator starts at x[t].
    response = signal.lfilter([1.0, -0.6], [1.0, -1.2, 0.5], x)
    y = response + 0.1 * np.std(response) * rng.standard_normal(x.size)
    assert feeds_through([(x, y)], linear_terms(2, 2, 0), level)
    assert choose_linear([(x, y)])[0] == (2, 2, 0)


def test_with_nothing_declared_the_rig_without_its_spring_starts_at_its_order():
    """The rig with its cubic spring taken out is a linear system of fourth order, driven with 800 N
    of unmeasured force on the mass the input drives: no nonlinearity is there to fake an order,
    and the start took ARX(8, 8). Least squares' larger orders ran free over the short check
    blocks a little better on all three rotations, beyond their spread and the margin, while each
    output-error fit there, searched from measured starts on the fit blocks, ran free over the
    check blocks several times worse than its least-squares start. Judged by their
    instrumental-variable estimates, the orders beyond four have no unique estimate and do not
    run free better."""
    scenario = Scenario(params=replace(Scenario().params, k3=0.0), disturbance_std=800.0)
    record = simulate(scenario, 1600, 2)
    orders, _ = choose_linear([(record.x, record.y)])
    assert orders == (4, 4, 1), orders


def test_with_nothing_declared_a_linear_structure_keeps_no_family_a_round_found_by_chance():
    """The rig with its cubic spring taken out, 800 N of unmeasured force, nothing declared: a
    linear system, nothing to add. On this record a filtered input nonlinearity (the square of a
    combination of x's lags, the combination searched on the residual that tests it) was
    significant in the first round as one free column; its test now counts the combination, and
    it is not. The generic polynomial is significant there and runs free over the check blocks
    better than the start by more than their margin; over the held-out tails, which no choice
    saw, the grown model runs free worse than the start, and the loop returns the start."""
    scenario = Scenario(params=replace(Scenario().params, k3=0.0), disturbance_std=800.0)
    record = simulate(scenario, 1600, 15)
    result = refine([(record.x, record.y)], None)
    assert result.rounds[0].added is not None and result.rounds[0].criterion == "one-step"
    assert "filtered_input_nonlinearity" not in [s.name for s in result.rounds[0].scores if s.significant]
    assert result.effects_withdrawn == (result.rounds[0].added.name,)
    assert result.held_out is not None and not result.held_out.kept
    assert not result.effects_added and result.refined.terms == result.declared.terms


def test_on_a_short_record_a_nonlinearity_does_not_buy_the_start_more_orders():
    """400 samples of a second-order system seen through a mild quadratic sensor: ARX(9, 9)
    with x[t] simulated the three held-out rotations 13 % better than ARX(2, 2), by the best
    linear approximation of the curve over samples a few hundred parameters' worth of fits had
    seen, and was the start. Its 19 parameters, paid for as the Bayesian information criterion
    pays on the samples held out, keep the start at the system's order (with a constant: the
    square's mean moves the output off zero)."""
    rng = np.random.default_rng(2)
    x = rng.standard_normal(400)
    response = signal.lfilter([0.0, 1.0, 0.5], [1.0, -1.2, 0.5], x)
    y = response + 0.1 * response**2 + 0.1 * np.std(response) * rng.standard_normal(400)
    orders, terms = choose_linear([(x, y)])
    assert orders == (2, 2, 1) and terms[:4] == linear_terms(2, 2, 1), (orders, terms)


def test_with_nothing_declared_an_output_far_from_zero_starts_from_a_model_with_a_constant():
    """An output at 50 times its spread from zero, the input about zero: an ARX without a constant
    reaches the operating point only by poles near one, a model that integrates its own past and
    runs free far off (the DC motor/generator's output sits at 4900 V, spread 880 V: its start
    without a constant ran free at RRSE 0.96). The start carries the constant and the system's
    orders, and runs free over a held-out stretch within a few times the noise."""
    rng = np.random.default_rng(5)
    n = 3000
    x = rng.standard_normal(n)
    response = signal.lfilter([0.0, 1.0, 0.5], [1.0, -1.2, 0.5], x)
    y = 50 * np.std(response) + response + 0.05 * np.std(response) * rng.standard_normal(n)
    orders, terms = choose_linear([(x[:2000], y[:2000])])
    assert orders == (2, 2, 1) and terms == (*linear_terms(2, 2, 1), Term()), (orders, terms)
    start = fit_narx([(x[:2000], y[:2000])], terms)
    free_run = start.simulate(x[2000:], y[2000:])[2:] - y[2002:]
    assert np.sqrt(np.mean(free_run**2)) < 0.2 * np.std(response)


def test_with_nothing_declared_an_output_about_zero_starts_without_a_constant():
    """The same system about zero: a constant would take nothing off the free run, and the start
    is the ARX of the system's orders alone."""
    rng = np.random.default_rng(5)
    x = rng.standard_normal(2000)
    response = signal.lfilter([0.0, 1.0, 0.5], [1.0, -1.2, 0.5], x)
    y = response + 0.05 * np.std(response) * rng.standard_normal(2000)
    assert choose_linear([(x, y)]) == ((2, 2, 1), linear_terms(2, 2, 1))


def test_a_model_the_input_barely_drives_is_no_start():
    """y[t] = 2.0003 y[t-1] − 1.0005 y[t-2] + 2·10⁻¹¹ x[t-1] + …: the order-2 least-squares fit
    on a rig record with a 10 kN dead zone, which only extrapolates the output's own past."""
    record = simulate(Scenario(disturbance_std=800.0), 2400, seed=1)
    checks = CheckSplit.of([(record.x, record.y)])
    terms = linear_terms(2, 2, 1)
    extrapolating = NARX(terms, np.array([2.0003, -1.0005, 2e-11, 2e-11]), np.zeros((4, 4)))
    assert not _is_start(extrapolating, checks)
    assert _is_start(checks.fitted(Structure(linear_terms(4, 4, 1))), checks)


def test_a_test_part_too_short_for_the_residual_tests_is_scored_and_says_which_it_skipped():
    """A hundred scored samples, as the coupled electric drives' benchmark tests on: the free
    run and one-step errors are scored, the residual tests named as skipped, not refused."""
    record = simulate(Scenario(disturbance_std=200.0), 600, seed=3)
    report = refine_record(record.x, record.y, EXACT_TERMS, [(0, 496)], (496, 600), initial=4, fs=record.fs)
    assert np.isfinite(report.before.free_run_rms) and np.isfinite(report.after.free_run_rms)
    assert report.after.skipped == ("ljung_box", "billings_voon", "billings_zhu", "spectrum")
    document = report.to_dict()
    assert document["tests"][0]["after"]["diagnostics"] is None
    assert any("too short for the residual tests" in note for note in document["notes"]), document["notes"]


def test_where_the_held_out_tails_favour_least_squares_the_refined_model_is_fitted_so():
    """Nothing declared, 4000 samples of the rig with a 10 kN input dead zone (200 N of
    unmeasured force): the loop names the dead zone and the rig's spring, and the check blocks
    chose output error for them; the search on all the heads ended where the model ran free over
    the held-out tails nearly seven times as far off as the least-squares fit of the same terms,
    and over a record from another seed four and a half times as far as the model refined from
    the rig's structure. The tails now choose the estimator as they choose the start's."""
    scenario = Scenario(disturbance_std=200.0, effects=Effects.parse(["dead_zone=10000"]))
    record, other = simulate(scenario, 4000, 1), simulate(scenario, 4000, 50_001)
    result = refine([(record.x, record.y)], None)
    assert [effect.name for effect in result.effects_added] == ["input_dead_zone", "cubic_stiffness"]
    assert result.estimator == "least squares"
    rig = refine([(record.x, record.y)], EXACT_TERMS)
    free_run, rig_free_run = (validate(r.refined, [(other.x, other.y)]).free_run.rms for r in (result, rig))
    assert free_run < 1.5 * rig_free_run, (free_run, rig_free_run)


def test_the_loop_hands_on_the_least_squares_fit_of_the_structure_it_refined():
    """The tails choose the refined model's estimator against the least-squares fit of its
    structure on all the heads (the test above), which the loop made already, in a thread beside
    the output-error check: it hands that fit on (``Grown.least_squares``), the same to the last
    bit as a fit made afresh, where the tails' choice made it a second time. (On half the record
    above, from the rig's structure: a loop that grows it and ends on output error, as that one
    does, at a third of its cost.)"""
    scenario = Scenario(disturbance_std=200.0, effects=Effects.parse(["dead_zone=10000"]))
    record = simulate(scenario, 2000, 1)
    split = held_out_tails([(record.x, record.y)])
    assert split is not None
    heads, _ = split
    grown = loop_on(heads, EXACT_TERMS, None, DEFAULT_ALPHA, MAX_ROUNDS, True, lambda stage: None, map, map)
    assert grown.refinement.estimator == "output error" and grown.structure.terms != grown.start.terms
    fitted, _ = fitted_on_all(heads, grown.structure)
    assert grown.least_squares.terms == fitted.terms
    assert np.array_equal(grown.least_squares.theta, fitted.theta)
    assert not np.array_equal(grown.refinement.refined.theta, fitted.theta)


def test_effects_the_held_out_tails_do_not_support_are_withdrawn_and_the_start_returned():
    """Nothing declared, a record whose steps grow: on the check blocks x² lowered the free run;
    beyond the range it was fitted on it grows without bound. Without the held-out comparison
    the loop returned input_nonlinearity (with moving-average noise) and the test part's free run
    went 2.24 → 2.79; held out from every choice, the estimation record's tail shows it worse."""
    x, y = growing_steps(2400, seed=1)
    report = refine_record(x, y, None, [(0, 1600)], (1600, 2400))
    result = report.refinement
    held_out = result.held_out
    assert held_out is not None and held_out.samples == 320
    assert held_out.refined_rms > held_out.start_rms and not held_out.better
    assert not held_out.kept and held_out.best_tried == "input_nonlinearity"
    assert process_effects(result) == () and "input_nonlinearity" in result.effects_withdrawn
    # The even part's mean drives the output off zero: the start carries a constant.
    assert result.refined.terms == result.declared.terms == linear_terms(*result.orders, constant=True)
    assert report.after.free_run_rms <= report.before.free_run_rms
    document = report.to_dict()
    assert document["held_out"]["refined_returned"] is False
    assert document["held_out"]["start_free_run_rms"] < document["held_out"]["refined_free_run_rms"]
    assert document["held_out"]["gain"] < document["held_out"]["threshold"]
    (note,) = [note for note in document["notes"] if "could not support the effects" in note]
    assert "320 samples" in note and "input_nonlinearity" in note


def test_on_a_short_record_effects_its_tail_does_not_support_are_withdrawn_and_the_start_returned():
    """Five hundred estimation samples whose steps grow: too short, once, to hold a tail out, the
    loop added moving-average noise, an offset and the generic polynomial, and the test part's
    free run went 2.37 → 5.96. A tail of a hundred samples, held out from every choice but the
    linear start's, shows the refined model no better; the start is returned and the report says so."""
    x, y = growing_steps(750, seed=3)
    report = refine_record(x, y, None, [(0, 500)], (500, 750))
    result = report.refinement
    held_out = result.held_out
    assert held_out is not None and held_out.samples == 100
    assert not held_out.kept and held_out.best_tried is not None
    assert process_effects(result) == () and held_out.best_tried in result.effects_withdrawn
    assert result.refined.terms == result.declared.terms
    assert report.after.free_run_rms <= report.before.free_run_rms
    document = report.to_dict()
    assert document["held_out"]["orders_saw_tails"] is True
    (note,) = [note for note in document["notes"] if "could not support the effects" in note]
    assert "100 samples no choice but the linear orders saw" in note and held_out.best_tried in note


def test_on_a_short_record_a_kept_model_that_diverges_on_its_test_part_is_reported_beyond_its_range():
    """Five hundred estimation samples whose steps grow, nothing declared: the loop adds missing
    lags, cubic stiffness and an offset, and the hundred-sample tail approves them. The test part
    reaches more than twice the estimation records' largest input, and the kept polynomial,
    bounded over every sample it was fitted and judged on (run from the records' start, tails
    too), escapes there. The tails cannot show it, nor a free run over the estimation records:
    they never reach the state it escapes from. The report says why: the refined model's
    amplitude range, measured on the estimation inputs scaled up, ends below the test part's
    input scale, where the linear start's has no limit."""
    x, y = growing_steps(750, seed=2)
    report = refine_record(x, y, None, [(0, 500)], (500, 750))
    held_out = report.refinement.held_out
    assert held_out is not None and held_out.kept and held_out.better
    # The refined model's free run over the estimation record, from its start, stays in range.
    refined = report.refinement.refined
    whole = refined.simulate(x[:500], y[:500])
    assert np.max(np.abs(whole)) < np.max(np.abs(y[:500]))
    document = report.to_dict()
    test = document["tests"][0]
    assert test["verdict"] == "diverged" and test["coverage"]["extrapolates"]
    scale = test["coverage"]["input_scale"]
    assert scale == pytest.approx(np.max(np.abs(x[500:])) / np.max(np.abs(x[:500])))
    ranges = document["amplitude_range"]
    assert ranges["declared"]["bounded_to"] is None and ranges["declared"]["diverges_at"] is None  # linear
    bounded_to, diverges_at = ranges["refined"]["bounded_to"], ranges["refined"]["diverges_at"]
    assert 1.0 <= bounded_to < diverges_at <= scale
    # The range read off directly: the refined model's own free run with the estimation input
    # scaled to its limit stays within the bound, and scaled to the next scale tried leaves it.
    for factor, escapes in ((bounded_to, False), (diverges_at, True)):
        run = refined.simulate(factor * x[:500], factor * y[:500])[refined.max_lag :]
        bound = RESTLESS * factor * np.max(np.abs(y[:500]))
        beyond = not np.all(np.isfinite(run)) or bool(np.max(np.abs(run)) > bound)
        assert beyond is escapes, factor
    said = f"bounded for inputs up to {bounded_to:g}× the estimation records' amplitude"
    assert (
        said in test["beyond_amplitude_range"] and f"reaches {scale:.2g}×" in test["beyond_amplitude_range"]
    )
    assert any(said in note and "the linear start does not" in note for note in document["notes"])


def test_on_the_coupled_drives_prbs_records_the_model_returned_runs_the_test_no_worse_than_its_start():
    """The PRBS record of ±1.5, 400 estimation samples, 100 tested (the benchmark's split): refined
    whole, the loop added moving-average noise and its free run over the test went 1.494 → 1.532
    ticks/s; the tail then held out, the start's output-error fit chosen on the heads ran 1.543.
    The model returned simulates the test no worse than the start. (The record of ±1 once went
    0.662 → 0.677 refined whole; the loop now returns a model no worse there with the tails not
    held out, not compared, or without the start chosen on them, so it tested none of the three.)"""
    benchmark_data("coupled-drives", "DATAPRBS.csv")
    drives = coupled_drives(2, prbs=True)
    report = refine_records(drives.estimation, list(drives.tests.values()), None, drives.initial)
    assert report.after.free_run_rms <= report.before.free_run_rms, (report.before, report.after)


def _bilinear(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """y[t] = 0.5 y[t-1] + x[t-1] + 0.3 x[t-1]·y[t-1], x uniform on [0, 1], with 2 % output noise:
    a gain that goes with the input, as a motor/generator's does with its field."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, 1.0, n)
    y = np.zeros(n)
    for t in range(1, n):
        y[t] = 0.5 * y[t - 1] + x[t - 1] + 0.3 * x[t - 1] * y[t - 1]
    return x, y + 0.02 * np.std(y) * rng.standard_normal(n)


def _free_run_shares(result: Refinement, x: np.ndarray, y: np.ndarray, start: int) -> tuple[float, float]:
    """The declared and refined models' free-run RMS over (x, y) after ``start`` samples, as
    shares of the output's spread."""
    return tuple(
        float(np.sqrt(np.mean((m.simulate(x, y)[start:] - y[start:]) ** 2)) / np.std(y[start:]))
        for m in (result.declared, result.refined)
    )


def test_where_no_named_effect_explains_the_data_the_generic_polynomial_is_added():
    """Without the bilinear family no named family holds the product x[t-1]·y[t-1]: the generic
    polynomial, offered after them, brings it, and the free run over another record falls
    five-fold (0.10 → 0.02 of the output's spread)."""
    x, y = _bilinear(500, 1)
    declared = parse_terms(["y[t-1]", "x[t-1]", "1"])
    offered = [effect for effect in candidate_effects(declared) if effect.name != "bilinear"]
    result = refine([(x, y)], declared, effects=offered)
    assert result.effects_added[0].name == "polynomial", result.effects_added
    assert Term.of([Factor("y", 1), Factor("x", 1)]) in result.refined.terms
    start, refined = _free_run_shares(result, *_bilinear(500, 2), 1)
    assert refined < start / 3, (start, refined)


def test_a_gain_that_goes_with_the_input_is_named_bilinear():
    """The same record with every family on offer: the product x[t-1]·y[t-1] is named first as
    dynamics the input modulates, and the free run over another record falls as far."""
    x, y = _bilinear(500, 1)
    result = refine([(x, y)], ["y[t-1]", "x[t-1]", "1"])
    assert result.effects_added[0].name == "bilinear", result.effects_added
    assert "y[t-1]*x[t-1]" in result.effects_added[0].terms
    start, refined = _free_run_shares(result, *_bilinear(500, 2), 1)
    assert refined < start / 3, (start, refined)


def _switched_drive(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A second-order drive whose damping the input switches, y[t] = (1.2 + 0.25·x[t-1])·y[t-1]
    − 0.5·y[t-2] + x[t-1], the input on or off (0 or 1) for four samples at a time, with 2 %
    output noise. A binary input is its own square: the input's powers hold nothing a linear
    model lacks."""
    rng = np.random.default_rng(seed)
    x = np.repeat(rng.integers(0, 2, n // 4 + 1).astype(float), 4)[:n]
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = (1.2 + 0.25 * x[t - 1]) * y[t - 1] - 0.5 * y[t - 2] + x[t - 1]
    return x, y + 0.02 * np.std(y) * rng.standard_normal(n)


def test_a_drive_that_switches_the_damping_is_named_bilinear_first():
    """Nothing but the modulation: the loop used to name moving-average noise and a power law of
    y (p = 1.2) before the generic polynomial brought the product; the bilinear family names it
    first, and the free run over another record falls from 0.49 to 0.02 of the output's spread
    (the 2 % noise)."""
    x, y = _switched_drive(600, 1)
    result = refine([(x, y)], ["y[t-1]", "y[t-2]", "x[t-1]", "1"])
    assert result.effects_added[0].name == "bilinear", result.effects_added
    assert "y[t-1]*x[t-1]" in result.effects_added[0].terms
    start, refined = _free_run_shares(result, *_switched_drive(600, 2), 2)
    assert refined < start / 10, (start, refined)


def test_a_refined_model_kept_on_the_held_out_tails_is_refitted_on_all_the_records():
    """A quadratic spring the rig's records plainly show: the refined model wins on the tails and is
    returned, its parameters estimated on all the estimation samples, not the heads alone."""
    record = simulate(
        Scenario(disturbance_std=200.0, effects=Effects(quadratic_stiffness2=3e5)), 6000, seed=2
    )
    x, y = record.x[:3000], record.y[:3000]
    result = refine([(x, y)], EXACT_TERMS, max_rounds=1)
    held_out = result.held_out
    assert held_out is not None and held_out.kept and held_out.better and held_out.samples == 600
    assert held_out.refined_rms < held_out.start_rms / 10
    assert result.effects_added[0].name == "quadratic_stiffness"
    assert result.declared.n_obs == len(y) - max_lag(EXACT_TERMS)
    assert result.refined.n_obs == len(y) - result.refined.max_lag


def test_a_refined_model_whose_one_free_run_over_the_tails_is_worse_is_not_the_better():
    """Nothing declared, a record of the rig with a quadratic spring: the refined model passed the
    comparison of pieces restarted from measured outputs (a gain of 96 % in their geometric mean)
    while its one free run over the tails was more than twice the start's, 0.317 against 0.143 m,
    and it was returned. A model that runs free worse over the tails is not the better; the loop
    returns the start where the refined model is not the better
    (:func:`test_effects_the_held_out_tails_do_not_support_are_withdrawn_and_the_start_returned`)."""
    assert HeldOut(800, 0.143, 0.317, gain=0.96, threshold=0.5).better is False
    assert HeldOut(800, 0.317, 0.143, gain=0.96, threshold=0.5).better is True


def test_a_record_of_a_few_hundred_samples_holds_a_short_tail_out_and_keeps_an_effect_it_shows():
    """Six hundred estimation samples of Coulomb friction: its 120-sample tail, three blocks,
    shows the refined model's free run a small part of the start's, and the refined model is kept.
    (Not a quadratic spring: its records stay in the well on one side of zero that the spring
    makes, and the laws that fit it there are kinked at a zero they never reach,
    tests/test_kinks.py.)"""
    record = simulate(Scenario(disturbance_std=200.0, effects=Effects(coulomb2=300.0)), 900, seed=2)
    report = refine_record(record.x, record.y, EXACT_TERMS, [(0, 900 * 2 // 3)], (600, 900))
    held_out = report.refinement.held_out
    assert held_out is not None and held_out.samples == 120 and held_out.kept and held_out.better
    assert report.refinement.effects_added and not report.refinement.effects_withdrawn
    assert report.after.free_run_rms < report.before.free_run_rms


def test_records_too_short_to_hold_a_tail_out_are_refined_whole_and_the_report_says_so():
    """Under 300 samples a tail would hold fewer than three blocks of the loop's shortest check."""
    record = simulate(Scenario(disturbance_std=200.0, effects=Effects(quadratic_stiffness2=3e5)), 450, seed=2)
    report = refine_record(record.x, record.y, EXACT_TERMS, [(0, 290)], (290, 450))
    assert report.refinement.held_out is None and report.refinement.effects_added
    assert any("too short to hold a tail out" in note for note in report.to_dict()["notes"])


def test_a_free_run_that_grows_without_bound_is_judged_diverged_though_finite():
    """y[t] = 1.05 y[t-1] + x[t-1] grows 1.05ⁿ: finite over 300 samples, far beyond the record."""
    rng = np.random.default_rng(4)
    x = rng.standard_normal(300)
    y = signal.lfilter([0.0, 1.0], [1.0, -0.5], x) + 0.1 * rng.standard_normal(300)
    terms = linear_terms(1, 1, 1)
    stable = NARX(terms, np.array([0.5, 1.0]), np.zeros((2, 2)))
    growing = replace(stable, theta=np.array([1.05, 1.0]))
    refinement = Refinement(stable, growing)
    comparison = compare(refinement, [(x, y)], x, y, 0, None, 0)
    assert np.isfinite(comparison.after.free_run_rms) and comparison.after.diverged
    assert not comparison.before.diverged and comparison.verdict == "diverged"
    (test,) = RefinementReport(refinement, (comparison,)).to_dict()["tests"]
    assert test["verdict"] == "diverged" and test["after"]["diverged"] and not test["before"]["diverged"]


STIFFNESS_FAMILIES = ("cubic_stiffness", "quadratic_stiffness", "power_law_stiffness")


@cache
def quadratic_spring_refined() -> tuple[Records, Refinement, tuple[str, ...]]:
    """The rig's quadratic spring (1600 samples, seed 1) refined from linear:4,4 with the three
    stiffness families alone, and the stages told: the loop two tests read, made once a process."""
    record = simulate(
        Scenario(disturbance_std=200.0, effects=Effects(quadratic_stiffness2=3e5)), 1600, seed=1
    )
    records = [(record.x, record.y)]
    declared = linear_terms(4, 4, 1)
    families = [effect for effect in candidate_effects(declared) if effect.name in STIFFNESS_FAMILIES]
    told: list[str] = []
    result = refine(records, declared, effects=families, progress=told.append)
    return records, result, tuple(told)


def test_a_term_that_a_later_addition_makes_redundant_is_pruned_and_the_report_names_it():
    """The rig's quadratic spring from linear:4,4: the cubic spring, added first, stands in for it
    with four terms; y[t-2]³ pays on the check blocks' free run until the quadratic spring is in,
    and not after. Pruned back after the rounds (Piroddi & Spinelli), it goes first, and the
    last round names what went; each round reports the candidates it compared, the gain it saw
    and the gain needed."""
    records, result, _ = quadratic_spring_refined()
    ((x, y),) = records
    declared = linear_terms(4, 4, 1)
    assert [effect.name for effect in result.effects_added] == ["cubic_stiffness", "quadratic_stiffness"]
    report = RefinementReport(result, (compare(result, records, x, y, 0, None, 0),))
    rounds = report.to_dict()["rounds"]
    assert [step["added"] for step in rounds] == ["cubic_stiffness", "quadratic_stiffness", None]
    *unpruned, (redundant, *_) = [parse_terms(step["pruned"]) if step["pruned"] else () for step in rounds]
    assert unpruned == [(), ()] and redundant.name == "y[t-2]^3"
    pruned = parse_terms(rounds[-1]["pruned"])
    cubic, quadratic = (tuple(parse_terms(effect.terms)) for effect in result.effects_added)
    assert result.refined.terms == (*declared, *cubic, *quadratic) and not set(pruned) & set(
        cubic + quadratic
    )
    # Made redundant by the addition: it paid on the check blocks before, and does not after.
    heads, _ = held_out_tails(records)
    checks = CheckSplit.of(heads)
    before = (*declared, *(term for term in cubic + pruned if term.name.endswith("^3")))
    assert checks.error(Structure(tuple(t for t in before if t != redundant))) > checks.error(
        Structure(before)
    )
    after = (*result.refined.terms, *pruned)
    assert checks.error(Structure(tuple(t for t in after if t != redundant))) <= checks.error(
        Structure(after)
    )
    # Each round's choice: how many candidates it compared, the gain it saw against the gain needed.
    for step, document in zip(result.rounds, rounds, strict=True):
        assert document["candidates_tried"] == step.tried > 0
        assert document["gain"] == step.gain and document["threshold"] == step.threshold
    assert all(step["gain"] >= step["threshold"] for step in rounds[:2]), rounds
    assert rounds[-1]["gain"] < rounds[-1]["threshold"], rounds[-1]


def hammerstein(n: int, seed: int, noise: float) -> tuple[np.ndarray, np.ndarray]:
    """y[t] = 1.2·y[t-1] − 0.5·y[t-2] + x[t-1] + 0.4·x[t-1]², white x, read with white noise of
    ``noise`` times the output's std."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=n)
    clean = signal.lfilter([0.0, 1.0], [1.0, -1.2, 0.5], x + 0.4 * x**2)
    return x, clean + noise * np.std(clean) * rng.normal(size=n)


def test_the_pruning_takes_an_earlier_effects_terms_but_never_its_last():
    """x[t-2]² and x[t-2]³, which the Hammerstein system lacks, brought in by an earlier round as
    one effect, and x[t-1]², which it has, added after it. By the check blocks' free run (least
    squares) neither pays: without both it is lower than with either. The pruning takes one and
    keeps the other, the effect's last term: its round added the effect for a gain beyond a
    threshold, and "no higher without it" on the same blocks is not the evidence to withdraw it
    whole (on Silverbox such a removal drifted over a new record)."""
    records = [hammerstein(1500, seed=3, noise=0.1)]
    checks = CheckSplit.of(records)
    declared, later = tuple(linear_terms(2, 2, 1)), tuple(parse_terms(["x[t-1]^2"]))
    earlier = tuple(parse_terms(["x[t-2]^2", "x[t-2]^3"]))
    either = min(checks.error(Structure((*declared, term, *later))) for term in earlier)
    assert checks.error(Structure(declared + later)) <= either
    effects = [
        EffectScore(
            name, "", 0.1, -1.0, tuple(term.name for term in terms), (9.0,) * len(terms), (0.0,) * len(terms)
        )
        for name, terms in (("input_nonlinearity", earlier), ("filtered_input_nonlinearity", later))
    ]
    rounds = [Round(1.0, 0.01, 2, (effect,), effect) for effect in effects]
    everything = Structure((*declared, *earlier, *later))
    pruned, (taken,) = pruned_back(everything, declared, rounds, checks, map, output_error=False)
    (kept,) = set(earlier) - {taken}
    assert pruned.terms == tuple(term for term in everything.terms if term != taken)
    assert kept in pruned.terms


def _hammerstein_beside_a_spare_term() -> tuple[
    list[tuple[np.ndarray, np.ndarray]], CheckSplit, Term, Structure
]:
    """A Hammerstein system's record, its check split, the system's own x[t-1]², and the linear
    structure holding it beside a spare x[t-1]³."""
    records = [hammerstein(1500, seed=3, noise=0.1)]
    needed, spare = parse_terms(["x[t-1]^2", "x[t-1]^3"])
    return records, CheckSplit.of(records), needed, Structure((*linear_terms(2, 2, 1), needed, spare))


def test_a_removal_the_pruning_refuses_on_its_run_over_the_check_blocks_is_not_judged_in_full():
    """The pruning takes a removal only where the check blocks' figure without the terms stays
    within the ceiling (:func:`models.pruning.pruned_back`). A removal whose run over the check
    blocks is already beyond the ceiling is refused on that run's RMS, a bound below its figure,
    and not asked whether it comes to rest: the Hammerstein system's own x[t-1]² taken out, the
    figure judged in full is beyond the ceiling as well, and the split keeps no figure for it."""
    records, checks, needed, everything = _hammerstein_beside_a_spare_term()
    ceiling = _ceiling(everything, checks, output_error=False)
    assert ceiling is not None
    assert _first_removal(everything, [(needed,)], ceiling, checks, map) is None
    without = replace(everything, terms=tuple(term for term in everything.terms if term != needed))
    assert CheckSplit.of(records).error(without) > ceiling.least_squares
    assert (without, False) not in checks._errors


def test_the_pruning_searches_its_output_error_bound_only_where_a_removal_passes_by_least_squares():
    """The pruning's bound by output error (the structure's output-error fit on the fit parts, a
    search) is read only where a removal passes by least squares, or that figure is not finite:
    sent ahead to a worker as the rounds end (``CheckSplit.judge_ahead``), the removals'
    least-squares judgements go on beside its search, where they waited for it. The Hammerstein
    system's own x[t-1]² taken out is refused by least squares, and the bound is not searched;
    read, it is the figure searched here, where it is below least squares'."""
    records, checks, needed, everything = _hammerstein_beside_a_spare_term()
    ceiling = _ceiling(everything, checks, output_error=True)
    assert ceiling is not None
    assert _first_removal(everything, [(needed,)], ceiling, checks, map) is None
    assert (everything, True) not in checks._errors and everything not in checks._tuned
    simulated = CheckSplit.of(records).error(everything, tuned=True)
    assert np.isfinite(simulated)
    assert ceiling.output_error == (simulated if simulated < ceiling.least_squares else None)
    assert checks.error(everything, tuned=True) == simulated


def test_judgements_sent_ahead_are_read_as_made_here_and_sent_once():
    """``CheckSplit.judge_ahead`` sends structures to the workers at once, each to be judged in
    a split of its own, and the split goes on; ``error``, ``judge`` and ``tuned`` read those
    judgements where they would make them: the figures and the output-error fits this process
    makes, to the bit, whichever structure is asked for first, each sent once. With the builtin
    map they are made when first read."""
    records = [hammerstein(1500, seed=3, noise=0.1)]
    linear = tuple(linear_terms(2, 2, 1))
    structures = [Structure(linear), Structure((*linear, *parse_terms(["x[t-1]^2"])))]
    here = CheckSplit.of(records)
    figures = [here.error(structure, tuned=True) for structure in structures]
    assert len(set(figures)) == 2 and all(np.isfinite(figures))
    with ProcessPoolExecutor(2) as pool:
        for workers in (map, pool.map):
            sent: list[Structure] = []

            def sending(function, jobs, workers=workers, sent=sent):
                jobs = list(jobs)
                sent.extend(structure for structure, _ in jobs)
                return workers(function, jobs)

            there = CheckSplit.of(records)
            there.judge_ahead(structures, sending, tuned=True)
            there.judge_ahead(structures, sending, tuned=True)
            assert there.error(structures[1], tuned=True) == figures[1]
            assert list(there.judge(structures, sending, tuned=True)) == figures
            assert sent == structures
            for structure in structures:
                assert np.array_equal(there.tuned(structure).theta, here.tuned(structure).theta)
            assert not there._ahead


# Minutes of output-error searches on a long record: `make slow`. `python -m bench.measured --only
# silverbox`'s linear:10,10 row takes the same path on the measured data.
@pytest.mark.slow
def test_a_family_whose_least_squares_model_diverges_is_judged_by_output_error_from_the_model():
    """Silverbox's physics (a mass, a damper and a hardening spring, sampled at ten times its
    resonance) with an offset on the sensor, from ``linear:10,10``: once the offset and Coulomb
    friction are in, the cube of a combination of the output's lags (the spring) explains the
    residual, but its least-squares model diverges on the check blocks, as every family's does.
    Judged by output error, its terms grown at zero from the current model's fit, it lowers the
    check blocks' free run and is added, decided by "output error" (judged by least squares alone,
    the loop took power-law damping there on the simulation criterion)."""
    x, y = DuffingOscillator().record(6000, cubic_share=0.3, noise_share=0.01, offset_share=0.3, seed=1)
    result = refine([(x, y)], linear_terms(10, 10), max_rounds=3)
    names = [step.added.name if step.added else None for step in result.rounds]
    assert names == ["offset", "coulomb_friction", "unmeasured_nonlinearity"], names
    assert result.rounds[-1].criterion == "output error"
    heads, _ = held_out_tails([(x, y)])
    checks = CheckSplit.of(heads)
    terms = linear_terms(10, 10)
    for step in result.rounds:
        assert step.added is not None
        terms += parse_terms(step.added.terms)
    # The premise: the spring's least-squares model diverges on the check blocks.
    assert checks.error(Structure(terms)) == np.inf
    before, after = result.rounds[-1].check_rms
    assert after <= (1 - check_noise(checks.check)) * before, (before, after)


def test_a_searched_law_does_not_stand_in_for_the_rigs_cubic_spring_and_a_contact_beside_it():
    """The rig's own cubic spring with a Hertzian contact, |y|^1.5·sign y, planted beside it, from
    linear:4,4 (1600 samples): a single power law at an exponent between the linear and the cubic
    law explains more of the start's one-step residual than the cubic alone, and with the
    contact's exponent searched again beside the cubic the two explain more still, beyond their
    further terms. The loop names the rig's spring, then the contact at its own exponent, not the
    blend. On the rig without its cubic spring the contact alone is named, though the cubic
    alone would be significant there too: beside the law it explains next to nothing."""
    declared = linear_terms(4, 4, 1)
    families = [effect for effect in candidate_effects(declared) if effect.name in STIFFNESS_FAMILIES]

    def refined(scenario: Scenario) -> Refinement:
        record = simulate(scenario, 1600, seed=1)
        return refine([(record.x, record.y)], declared, effects=families)

    def exponent(effect: EffectScore) -> float | None:
        return Term.parse(effect.terms[0]).factors[0].parameter

    contact = Scenario(disturbance_std=200.0, effects=Effects(hertz_contact2=5e4))
    alone = refined(replace(contact, params=replace(contact.params, k3=0.0)))
    assert [effect.name for effect in alone.effects_added] == ["power_law_stiffness"]
    assert exponent(alone.effects_added[0]) == pytest.approx(1.5, abs=0.05)
    assert any(score.name == "cubic_stiffness" and score.significant for score in alone.rounds[0].scores)
    result = refined(contact)
    # The premise: in the first round the blend ranks before the cubic.
    scores = {score.name: score for score in result.rounds[0].scores}
    blend, cubic = scores["power_law_stiffness"], scores["cubic_stiffness"]
    assert blend.significant and cubic.significant and blend.bic_change < cubic.bic_change
    assert 1.8 < (exponent(blend) or 0) < 2.6, blend.terms
    assert [effect.name for effect in result.effects_added] == ["cubic_stiffness", "power_law_stiffness"]
    assert exponent(result.effects_added[1]) == pytest.approx(1.5, abs=0.05)


def test_a_round_counts_the_candidates_its_look_ahead_compared():
    """The rig's quadratic spring from linear:4,4 with three stiffness families on offer: once the
    first in the one-step order clears, the round judges the next ones on the check blocks as
    contenders, and, where one gains enough more, the round after each
    (:func:`models.round_criteria.looked_ahead`). Every family judged on the check blocks is told as
    it is read; a round's candidates tried are all those told before the next round begins, the look
    ahead's among them."""
    _, result, told = quadratic_spring_refined()
    judged = [0]
    for stage in told:
        if stage.startswith("round ") and ": scoring" in stage and "looked ahead" not in stage:
            judged.append(0)
        judged[-1] += stage.endswith(" on the check blocks")
    one_step = [
        (step.tried, judged[number])
        for number, step in enumerate(result.rounds, start=1)
        if step.criterion == "one-step"
    ]
    assert len(one_step) == 2 and max(told_of for _, told_of in one_step) > 1, told
    assert all(tried == told_of for tried, told_of in one_step), (one_step, told)


def hammerstein_cubic(n: int, seed: int, noise: float) -> tuple[np.ndarray, np.ndarray]:
    """y[t] = 1.2·y[t-1] − 0.5·y[t-2] + x[t-1] + 0.3·x[t-1]³, x white about 0.5, read with white
    noise of ``noise`` times the output's std: about its mean the cube holds a square, which the
    generic polynomial's products of the lags can take part of."""
    rng = np.random.default_rng(seed)
    x = 0.5 + rng.normal(size=n)
    clean = signal.lfilter([0.0, 1.0], [1.0, -1.2, 0.5], x + 0.3 * x**3)
    return x, clean + noise * np.std(clean) * rng.normal(size=n)


def test_a_generic_block_a_later_effect_made_redundant_is_pruned_whole_and_the_report_says_so():
    """The generic polynomial, added first, takes a share of the cube's square off the check blocks'
    free run; the input's cube, added after it, makes all ten of its terms redundant. The pruning
    takes the block whole, its round is reported pruned whole and its effect is no longer among
    those added; the same terms brought by a named family (bilinear) keep their last."""
    x, y = hammerstein_cubic(1500, seed=0, noise=0.05)
    records = [(x, y)]
    checks = CheckSplit.of(records)
    declared = tuple(linear_terms(2, 2, 1))
    generic = polynomial_effect(declared).terms
    cube = tuple(parse_terms(["x[t-1]^3", "x[t-2]^3"]))
    # The premise: the block paid before the cube, and does not after it.
    without_either = checks.error(Structure(declared))
    assert checks.error(Structure(declared + generic)) < (1 - check_noise(checks.check)) * without_either
    assert checks.error(Structure(declared + cube)) <= checks.error(Structure(declared + generic + cube))
    everything = Structure(declared + generic + cube)

    def pruned_after(first: str) -> tuple[Structure, tuple[Term, ...], list[Round]]:
        effects = [
            EffectScore(
                name, "", 0.1, -1.0, tuple(t.name for t in terms), (9.0,) * len(terms), (0.0,) * len(terms)
            )
            for name, terms in ((first, generic), ("input_nonlinearity", cube))
        ]
        rounds = [Round(1.0, 0.01, 2, (effect,), effect) for effect in effects]
        pruned, taken = pruned_back(everything, declared, rounds, checks, map, output_error=False)
        assert cube[0] in pruned.terms and set(taken) == set(everything.terms) - set(pruned.terms)
        return pruned, taken, without_pruned(rounds, taken)

    pruned, _, _ = pruned_after("bilinear")
    assert len(set(generic) & set(pruned.terms)) == 1, pruned.terms
    pruned, taken, rounds = pruned_after("polynomial")
    assert not set(generic) & set(pruned.terms), pruned.terms
    assert [step.pruned_whole for step in rounds] == [True, False]
    assert set(parse_terms(rounds[-1].pruned)) == set(taken) >= set(generic)
    declared_model, _ = fit_model(records, declared, 0, max_lag(declared))
    refined, _ = fit_model(records, pruned.terms, 0, max_lag(pruned.terms))
    result = Refinement(declared_model, refined, rounds=tuple(rounds))
    assert [effect.name for effect in result.effects_added] == ["input_nonlinearity"]
    report = RefinementReport(result, (compare(result, records, x, y, 0, None, 0),)).to_dict()
    assert [(step["added"], step["pruned_whole"]) for step in report["rounds"]] == [
        ("polynomial", True),
        ("input_nonlinearity", False),
    ]
    assert [effect["name"] for effect in report["effects_added"]] == ["input_nonlinearity"]


def _rig_less_its_spring_and_a_searched_family() -> tuple[Records, tuple[Term, ...], list[Effect], list[int]]:
    """A record of the rig, its linear part as the model, and the candidate families with one
    searched family more that notes the size of each model it is searched on (``searches``)."""
    x, y = paper_record(["cubic_stiffness1=4e6"], seed=4)
    records = [(x[:ESTIMATION], y[:ESTIMATION])]
    exact = tuple(parse_terms(EXACT_TERMS))
    terms = (*exact[:4], exact[-1])  # the rig's linear part: its cubic spring is missing
    searches: list[int] = []

    def cube(search: SearchInput) -> tuple[Term, ...]:
        searches.append(len(search.terms))
        return tuple(parse_terms(["y[t-1]^3", "y[t-2]^3"]))

    counted = Effect("counted", "the cubes of y's lags, searched for", (), "estimated", find=cube)
    effects = [*candidate_effects(terms), counted]
    return records, terms, effects, searches


def test_a_model_scored_again_takes_the_families_kept_for_it_and_no_other_model_does():
    """The loop scores a model again after looking one round ahead and before the simulation
    criteria (``ScoringKept``): the families built for it then are not built again, and the
    scores, with more families offered or every regressor ranked, are those of a fresh scoring to
    the last digit (the level α/M counts the families offered now). Another model, or the same
    with moving-average terms, has its families built anew: a kept family would be another
    model's residual's."""
    records, terms, effects, searches = _rig_less_its_spring_and_a_searched_family()
    kept = ScoringKept()

    def both(model: tuple[Term, ...], offered: list[Effect], noise: int = 0, rank: bool = False) -> None:
        again = score_effects(records, model, noise, offered, 0.01, rank=rank, kept=kept)
        assert again == score_effects(records, model, noise, offered, 0.01, rank=rank)

    both(terms, effects[5:])
    assert len(searches) == 2  # once kept, once fresh
    both(terms, effects)
    both(terms, effects, rank=True)
    assert len(searches) == 4  # the fresh ones only
    both(terms[1:], effects)
    both(terms, effects, noise=1)
    assert searches[4:] == [4, 4, 5, 5]  # built for each other model, kept and fresh
    assert score_effects(records, terms, 0, effects, 0.01).scores[-1].significant


def test_the_structure_a_look_ahead_chose_keeps_its_families_while_the_round_scores_its_own_again():
    """A round that looks ahead scores two structures of the next round, then its own model
    again (the hysteresis family ranked on it), and the next round scores the structure the look
    chose: that structure's families, searched ones among them, are taken from the loop's
    ``ScoringKept`` rather than built again, and its scores are a fresh scoring's to the last
    digit. The models kept are the last two asked for: the round's own model, asked for after
    both looked-ahead ones, has its families built anew."""
    records, terms, effects, searches = _rig_less_its_spring_and_a_searched_family()
    kept = ScoringKept()
    one, other = (tuple(parse_terms(extra)) for extra in (["y[t-1]^3"], ["y[t-1]^2"]))
    round_model, first_ahead, chosen = terms, (*terms, *one), (*terms, *other)
    for model in (round_model, first_ahead, chosen):
        score_effects(records, model, 0, effects, 0.01, kept=kept)
    assert searches == [5, 6, 6]
    score_effects(records, round_model, 0, effects, 0.01, rank=True, kept=kept)
    assert searches[3:] == [5]  # asked for after both looked-ahead structures: built anew
    again = score_effects(records, chosen, 0, effects, 0.01, kept=kept)
    assert searches[4:] == []  # the look's choice: kept
    score_effects(records, first_ahead, 0, effects, 0.01, kept=kept)
    assert searches[4:] == [6]  # the third model back: let go
    assert again == score_effects(records, chosen, 0, effects, 0.01)


def test_a_narmax_fit_a_scoring_made_is_taken_by_a_later_fit_on_the_same_records_to_the_bit():
    """Scoring a model with moving-average terms fits it by extended least squares on all the
    records (the pseudo-linear regression's innovations); the loop keeps that fit
    (``ScoringKept.fits``), and the comparison of the rounds' models on the held-out tails,
    which fits each earlier round's structure on the same records, takes it from there rather
    than making it again: the same model to the last bit as a fit made afresh. Another
    structure's fit is made anew (and kept)."""
    records, terms, effects, _ = _rig_less_its_spring_and_a_searched_family()
    structure = Structure(terms, noise_lags=2)
    kept = ScoringKept()
    score_effects(records, terms, 2, effects[-1:], 0.01, kept=kept, lag=max_lag(terms))
    fits = kept.fits
    scoring_fit = fits.get((terms, 2, max_lag(terms), None, False))
    assert scoring_fit is not None
    made = fitted_on_all(records, structure, fits)
    assert made is scoring_fit and fitted_on_all(records, structure, fits) is made  # not made again
    fresh, noise = fitted_on_all(records, structure)
    np.testing.assert_array_equal(made[0].theta, fresh.theta)
    np.testing.assert_array_equal(made[0].covariance, fresh.covariance)
    np.testing.assert_array_equal(made[1], noise)
    other = replace(structure, noise_lags=1)
    assert fits.get((terms, 1, max_lag(terms), None, False)) is None
    np.testing.assert_array_equal(
        fitted_on_all(records, other, fits)[0].theta, fitted_on_all(records, other)[0].theta
    )
    assert fits.get((terms, 1, max_lag(terms), None, False)) is not None


def test_the_hysteresis_family_judged_on_its_free_run_is_judged_in_full_only_where_it_could_win():
    """Where the one-step criterion decided a round, the hysteresis family's ranked regressors are
    judged on the check blocks' free run (``output_state_by_simulation``): a structure whose run
    over the check blocks is already beyond the bar, the first's figure less the further gain,
    cannot be chosen, and is not asked whether it comes to rest (its run's RMS, a bound below
    its figure, answers). The decision and its figure are those of every structure judged in
    full, and the split holds no figure for one judged against the bound."""
    x, y = paper_record(["cubic_stiffness1=4e6", "hysteresis2=3e4"], seed=4)
    records = [(x[:ESTIMATION], y[:ESTIMATION])]
    exact = tuple(parse_terms(EXACT_TERMS))
    current = Structure((*exact[:4], exact[-1]))  # the rig's linear part: its cubic spring is missing
    offered = candidate_effects(current.terms)
    (hysteresis,) = [effect for effect in offered if effect.name == HYSTERESIS]
    scores = scored(records, current, offered, DEFAULT_ALPHA, map, map).scores
    (cubic,) = [score for score in scores if score.name == "cubic_stiffness"]
    states = scored(records, current, [hysteresis], DEFAULT_ALPHA, map, map, True).scores
    in_full = CheckSplit.of(records)
    check = in_full.error(current)
    with_cubic = replace(current, terms=current.terms + parse_terms(cubic.terms))
    first = (cubic, "one-step", with_cubic, in_full.error(with_cubic))
    bar = first[3] - SIMULATION_GAIN * check
    for ranked, expected in ((states, None), (states, "hysteresis")):
        checks = CheckSplit.of(records)
        decided, simulated = output_state_by_simulation(
            first if expected is None else (*first[:3], np.inf), ranked, current, check, checks, map
        )
        trials = [
            replace(
                current,
                terms=current.terms + parse_terms(label for labels in score.ranked[:k] for label in labels),
            )
            for score in ranked
            for k in range(1, len(score.ranked) + 1)
        ]
        figures = [in_full.error(structure) for structure in trials]
        assert simulated == len(trials) > 1
        if expected is None:
            assert decided is None and min(figures) > bar
            # Each beyond the bar: none was judged in full, and none is kept as a figure.
            assert not any((structure, False) in checks._errors for structure in trials)
        else:
            assert decided is not None and decided[0].name == expected
            assert decided[3] == min(figures) and decided[2] == trials[int(np.argmin(figures))]


def test_a_figure_judged_against_a_bound_is_not_taken_for_the_figure():
    """The look ahead's contenders matter only where their check figure could win
    (``CheckSplit.judge``'s ``matters``): a model whose free run over the check blocks is already
    beyond that is not asked whether it comes to rest, and its run's RMS, finite, answers.
    Asked for its figure, or by a caller to whom that figure matters, the split judges it in
    full: it does not come to rest (a root outside the unit circle), so the figure is infinite,
    here and in the workers."""
    rng = np.random.default_rng(1)
    x = rng.standard_normal(3000)
    y = signal.lfilter([0.0, 1.0], [1.0, -0.9], x) + 0.01 * rng.standard_normal(3000)
    structure = Structure(tuple(parse_terms(["y[t-1]", "x[t-1]"])))
    fitted = CheckSplit.of([(x, y)]).fitted(structure)
    drifting = replace(fitted, theta=np.array([1.001, 1.0]))
    beyond, mattering = partial(operator.ge, 0.01), partial(operator.ge, 1e9)  # 0.01 >= figure, …
    with ProcessPoolExecutor(1) as pool:
        for workers in (map, pool.map):
            checks = CheckSplit.of([(x, y)])
            checks._fitted[structure] = drifting
            (bound,) = checks.judge([structure], workers, matters=beyond)
            assert np.isfinite(bound) and not beyond(bound)
            assert list(checks.judge([structure], workers, matters=mattering)) == [np.inf]
            assert checks.error(structure) == np.inf
            assert list(checks.judge([structure], workers, matters=beyond)) == [np.inf]
    assert np.isfinite(CheckSplit.of([(x, y)]).error(structure))  # as fitted, it comes to rest


def test_two_effects_that_each_run_free_worse_alone_are_added_as_a_pair():
    """The 2-DOF rig with Coulomb friction on its measured mass, from the linear start the loop
    chooses there with nothing declared (orders (4, 4), delay 1, a constant). The friction
    explains nearly all of the start's one-step residual, yet its model alone runs free over the
    check blocks worse than the start, as the rig's own cubic spring alone does: each is fitted to
    the other's share of the residual too. Together they run free at a fraction of the start's
    figure. The friction is added first, decided as a pair, and the spring in a later round
    (before, no family cleared and the loop returned the start)."""
    scenario = Scenario(disturbance_std=200.0, effects=Effects.parse(["coulomb2=300"]))
    record = simulate(scenario, 1600, seed=1)
    records = [(record.x, record.y)]
    declared = linear_terms(4, 4, 1, constant=True)
    result = refine(records, declared)
    first = result.rounds[0]
    assert first.added is not None and first.added.name == "coulomb_friction", first
    assert first.criterion == "pair"
    start, alone = first.check_rms
    assert alone > start  # the premise: the friction alone runs free worse
    heads, _ = held_out_tails(records)
    checks = CheckSplit.of(heads)
    spring = (*declared, *parse_terms([f"y[t-{lag}]^3" for lag in range(1, 5)]))
    assert checks.error(Structure(spring)) > (1 - check_noise(checks.check)) * start  # nor the spring alone
    names = [effect.name for effect in result.effects_added]
    assert names[0] == "coulomb_friction", names
    assert {"cubic_stiffness", "unmeasured_nonlinearity"} & set(names), names
    assert result.check_rms < 0.5 * start
    # The held-out tails keep them, and the model simulates a record of another seed better.
    test = simulate(scenario, 4000, seed=50_001)
    before = validate(result.declared, [(test.x, test.y)]).free_run.rms
    assert validate(result.refined, [(test.x, test.y)]).free_run.rms < 0.5 * before


def test_a_leader_that_runs_free_worse_alone_is_judged_as_a_pair_before_a_stand_in_clears_by_little():
    """The 2-DOF rig with power-law damping on its measured mass (a spent held-out seed), from the
    linear start the loop chooses there with nothing declared. The damping law explains nearly all
    of the start's one-step residual and alone runs free over the check blocks worse than the
    start: it needs the rig's own cubic spring beside it. Coulomb friction, a stand-in, cleared on a
    fall short of the simulation criterion's share; with it in, the law never ran free better, and
    the held-out tails returned the start. Judged as a pair, pair against pair, the law leads and
    the spring follows (:func:`models.round_criteria.leader_as_pair`)."""
    scenario = Scenario(disturbance_std=200.0, effects=Effects.parse(["power_damping2=1000"]))
    record = simulate(scenario, 1600, seed=8113)
    records = [(record.x, record.y)]
    declared = linear_terms(4, 4, 1, constant=True)
    names = ("power_law_damping", "coulomb_friction", "cubic_stiffness")
    offered = [effect for effect in candidate_effects(declared) if effect.name in names]
    result = refine(records, declared, effects=offered, max_rounds=2)
    first = result.rounds[0]
    scores = {score.name: score for score in first.scores}
    law, friction = scores["power_law_damping"], scores["coulomb_friction"]
    # The premises on the loop's own check blocks: the law leads the one-step order and runs free
    # worse alone; the friction clears by more than the figure's standard error, less than the share.
    assert law.bic_change < friction.bic_change < 0, (law.bic_change, friction.bic_change)
    heads, _ = held_out_tails(records)
    checks = CheckSplit.of(heads)
    start = checks.error(Structure(tuple(declared)))
    assert first.check_rms[0] == pytest.approx(start)
    with_law = checks.error(Structure((*declared, *parse_terms(law.terms))))
    with_friction = checks.error(Structure((*declared, *parse_terms(friction.terms))))
    assert with_law > start, (with_law, start)
    assert (1 - SIMULATION_GAIN) * start < with_friction < (1 - check_noise(checks.check)) * start
    assert first.added is not None and first.added.name == "power_law_damping", first
    assert first.criterion == "pair"
    assert [effect.name for effect in result.effects_added] == ["power_law_damping", "cubic_stiffness"]
    assert result.held_out is not None and result.held_out.kept
    # The model simulates a record of another seed several times better than the start.
    test = simulate(scenario, 4000, seed=8113 + 50_000)
    before = validate(result.declared, [(test.x, test.y)]).free_run.rms
    assert validate(result.refined, [(test.x, test.y)]).free_run.rms < 0.25 * before


def test_a_record_that_starts_before_the_system_settled_is_estimated_from_where_it_settled():
    """The record's first few hundred samples hold a machine that was still warming up: fitted on
    the whole record, the pole comes out low and the free run over a record of the settled machine
    is more than twice as far off as that of the fit where it settled. The model fitted without
    the record's first part runs free over the held-out tail better, so it is the one returned,
    and the report says what was left out. A record of the settled machine keeps every sample."""
    declared = ["y[t-1]", "x[t-1]"]
    x, y = warming_drive(1500, 1)
    report = refine_records([(x, y)], [warming_drive(600, 101, settled=True)], declared)
    result = report.refinement
    assert result.settled_from and 0 < result.settled_from[0] <= 600, result.settled_from
    assert result.refined.n_obs == len(y) - result.settled_from[0] - 1
    assert any("record was left out" in note for note in report.to_dict()["notes"])
    whole = fit_narx([(x, y)], parse_terms(declared))
    test_x, test_y = warming_drive(600, 101, settled=True)
    on_whole = held_out_errors(whole, test_x, test_y, 1).free_run.rms
    assert report.after.free_run_rms < on_whole / 1.5, (report.after.free_run_rms, on_whole)
    assert abs(result.refined.theta[0] - 0.8) < 0.01, result.refined.theta
    settled = refine([warming_drive(1500, 1, settled=True)], declared)
    assert settled.settled_from == (), settled.settled_from


def test_with_nothing_declared_quadratic_damping_whose_lags_only_explain_together_is_named_first():
    """Quadratic damping on the rig's measured mass, nothing declared: the force reaches the
    sampled output as a near-cancelling combination of dy·|dy| at neighbouring lags, so that the
    family's best column alone failed its F test while the four together explained most of the
    residual. The family was scored as explaining nothing, power-law damping at its range's end
    (p = 1.8) took its place, and after nine rounds the held-out tail withdrew everything. The
    greedy selection now lets the next columns enter as a block where their joint F test passes:
    the family is significant in round 1, named first, and the model runs free over a record of
    another seed within twice the model refined from the rig's structure."""
    scenario = Scenario(disturbance_std=200.0, effects=Effects(quadratic_damping2=2e3))
    record, test = simulate(scenario, 1600, 1), simulate(scenario, 4000, 50_001)
    heads, _ = held_out_tails([(record.x, record.y)])
    start = linear_terms(4, 4, 1)
    scores = score_effects(heads, start, 0, candidate_effects(start), 0.01).scores
    first = min(scores, key=operator.attrgetter("bic_change"))
    assert first.name == "quadratic_damping" and first.explained > 0.5, (first.name, first.explained)
    found = refine([(record.x, record.y)], None)
    assert [e.name for e in found.effects_added][:1] == ["quadratic_damping"], found.effects_added
    rig = refine([(record.x, record.y)], EXACT_TERMS)
    free_run = validate(found.refined, [(test.x, test.y)]).free_run.rms
    assert free_run < 2 * validate(rig.refined, [(test.x, test.y)]).free_run.rms


def test_with_nothing_declared_a_periodic_force_enters_as_a_sinusoid_of_its_own_phase_and_is_named_first():
    """A 1000 N force at 12.5 Hz on the rig, nothing declared. Tested one wave at a time, the
    periodic family entered as the cosine alone (the sine was not significant by itself at the
    round's level), which took a sixth off the check blocks' free run where sine and cosine
    together take half; and moving-average noise, credited with the smooth residual the missing
    sine left, took the first round. A sinusoid's sine and cosine now enter together by their
    joint F test: the disturbance is significant whole, its terms take the noise's place first,
    and the model runs free over the record's continuation within twice the model refined from
    the rig's structure."""
    scenario = Scenario(disturbance_std=200.0, effects=Effects(sine_amplitude=1000.0, sine_frequency=12.5))
    samples = 1600
    record = simulate(scenario, samples + 4000, 2)
    x, y = record.x[:samples], record.y[:samples]
    heads, _ = held_out_tails([(x, y)])
    start = linear_terms(4, 4, 1)
    scores = score_effects(heads, start, 0, candidate_effects(start), 0.01).scores
    (periodic,) = [s for s in scores if s.name == "periodic_disturbance"]
    waves = [Term.parse(name).factors[0] for name in periodic.terms]
    assert sorted(w.signal for w in waves) == ["cos", "sin"], periodic.terms
    assert len({w.frequency for w in waves}) == 1, periodic.terms
    assert min(scores, key=operator.attrgetter("bic_change")).name == "periodic_disturbance"
    found = refine([(x, y)], None)
    assert [e.name for e in found.effects_added][:1] == ["periodic_disturbance"], found.effects_added
    rig = refine([(x, y)], EXACT_TERMS)
    test = [(record.x[samples:], record.y[samples:])]
    free_run = validate(found.refined, test, t0=samples).free_run.rms
    assert free_run < 2 * validate(rig.refined, test, t0=samples).free_run.rms
