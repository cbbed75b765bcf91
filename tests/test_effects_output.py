"""Effects on the output side and behind the sensor: saturation, power laws, an input dead zone
and backlash, hysteresis, a nonlinear spring on the unmeasured mass, a static nonlinearity between
two filters — their terms, their free run, and the loop naming each when it is planted."""

from __future__ import annotations

import functools
from dataclasses import replace

import numpy as np
import pytest
from scipy import linalg, signal, stats

from harness.hysteretic import BoucWenOscillator
from harness.rectified import rectified_drive
from models.assessment import assess
from models.checking import SETTLED_EVALUATIONS, free_run_rms
from models.effects import (
    EXPONENT_ALPHA,
    SearchInput,
    _search_part,
    candidate_effects,
    combination_parameters,
    integer_powers,
    linear_terms,
    output_limits,
    reads_magnitude,
)
from models.errors import InputError
from models.explanation import explain_refinement
from models.held_out import compare_on_tails
from models.narx import NARX, fit_narx, run_start
from models.output_error import fit_output_error
from models.refinement import RefinementReport, refine_record, refine_records
from models.round_criteria import DEFAULT_ALPHA
from models.scoring import score_effects
from models.terms import Factor, Term, bouc_wen, bouc_wen_step, max_lag, parse_terms, regressor_matrix
from models.validation import validate
from simulator.physics import PhysicalParameters
from simulator.simulate import BOUC_WEN_BETA, BOUC_WEN_GAMMA, Effects, Scenario, simulate
from simulator.theory import EXACT_TERMS, exact_narx

# The loop runs on the first 8000 samples and holds out the next 2000 (models.held_out); the
# models are judged on the last 2000.
ESTIMATION, HELD_OUT = 10_000, 2000

# One planted effect at a time, sized so that it, not the 200 N force disturbance, dominates the
# declared model's free-run error; with the parameter the loop must estimate for it: the dead
# zone's and the backlash's half-widths, the exponents ½ of the damping and 3/2 of the Hertzian
# contact, each to 1 % (2 % for the damping's exponent: 0.5 ± 0.01), and the level 1/(β + γ)
# the Bouc–Wen variable saturates at, to 2 %, its shape γ/β = 1 to 0.05: the two are estimated
# together, and the rig's z, on mass 2, is a forward difference at the sampling rate where the
# family's is the differential equation's solution.
PLANTED = [
    ("output_saturation", "sensor_range=0.08", None),
    ("power_law_damping", "power_damping2=1000", 0.5),
    ("power_law_stiffness", "hertz_contact2=5e4", 1.5),
    ("input_dead_zone", "dead_zone=10000", 10000.0),
    ("input_backlash", "backlash=5000", 5000.0),
    ("unmeasured_nonlinearity", "cubic_stiffness1=4e6", None),
    ("hysteresis", "hysteresis2=3e4", 1 / (BOUC_WEN_BETA + BOUC_WEN_GAMMA)),
]
ONE_PERCENT = ("power_law_stiffness", "input_dead_zone", "input_backlash")


@functools.cache
def planted(spec: str, x_scale: float = 1.0, y_scale: float = 1.0) -> RefinementReport:
    """The loop on the rig's record with one planted effect, its signals in units scaled by
    ``x_scale`` and ``y_scale``; made once a process (the tests below share the plain runs)."""
    record = simulate(
        Scenario(disturbance_std=200.0, effects=Effects.parse([spec])), ESTIMATION + HELD_OUT, seed=1
    )
    split = [(0, ESTIMATION)], (ESTIMATION, ESTIMATION + HELD_OUT)
    return refine_record(x_scale * record.x, y_scale * record.y, EXACT_TERMS, *split, fs=record.fs)


@pytest.mark.parametrize(("effect", "spec", "parameter"), PLANTED, ids=[name for name, *_ in PLANTED])
def test_a_planted_effect_is_named_first_and_the_free_run_error_halves(effect, spec, parameter):
    report = planted(spec)
    names = [e.name for e in report.refinement.effects_added]
    assert names and names[0] == effect, names
    assert report.after.free_run_rms <= report.before.free_run_rms / 2, (report.before, report.after)
    if parameter is not None:
        factor = Term.parse(report.refinement.effects_added[0].terms[0]).factors[0]
        estimated = factor.parameter
        if effect == "hysteresis":
            estimated = 2 * factor.parameter / (1 + factor.shape)  # the level z saturates at
            assert factor.shape == pytest.approx(BOUC_WEN_GAMMA / BOUC_WEN_BETA, abs=0.05)
        assert estimated == pytest.approx(parameter, rel=0.01 if effect in ONE_PERCENT else 0.02)


# The same records in other units (force in kN and displacement in µm; in 0.1 mN and km):
# every threshold of the loop is relative, so it must add the same effects in the same order, by
# the same criteria, and report its figures and the parameters it estimates in the new units (the
# dead zone's half-width in units of x, the plateaus in units of y). Least squares scales to
# rounding (its free run, a lightly damped recursion, carries that rounding to 10⁻⁹ of it); the
# output-error searches end in flat valleys where rounding alone moves their ends (by 10⁻⁷ to
# 10⁻⁵ of the free run here), far below the check's standard error (0.8 %) that the loop decides
# by: an absolute threshold anywhere would show at that scale.
@pytest.mark.parametrize(
    ("spec", "x_scale", "y_scale"), [("dead_zone=10000", 1e-3, 1e6), ("sensor_range=0.08", 1e4, 1e-3)]
)
def test_the_loop_decides_alike_whatever_the_units_of_the_signals(spec, x_scale, y_scale):
    plain, scaled = planted(spec), planted(spec, x_scale, y_scale)
    decisions = [(r.added.name, r.criterion) for r in plain.refinement.kept]
    assert decisions and [(r.added.name, r.criterion) for r in scaled.refinement.kept] == decisions
    assert scaled.before.free_run_rms == pytest.approx(y_scale * plain.before.free_run_rms, rel=1e-7)
    assert scaled.before.one_step_rms == pytest.approx(y_scale * plain.before.one_step_rms, rel=1e-9)
    for judged, judged_scaled in zip(plain.refinement.rounds, scaled.refinement.rounds, strict=True):
        np.testing.assert_allclose(judged_scaled.check_rms, np.multiply(y_scale, judged.check_rms), rtol=1e-5)
    assert scaled.after.free_run_rms == pytest.approx(y_scale * plain.after.free_run_rms, rel=1e-4)
    assert scaled.after.free_run_rms <= plain.before.free_run_rms * y_scale / 2
    if spec.startswith("dead_zone"):
        half_widths = [
            Term.parse(r.refinement.effects_added[0].terms[0]).factors[0].parameter for r in (plain, scaled)
        ]
        assert half_widths[1] == pytest.approx(x_scale * half_widths[0], rel=1e-9)
    else:
        limits = [r.refinement.refined.output_limits for r in (plain, scaled)]
        np.testing.assert_allclose(limits[1], np.multiply(y_scale, limits[0]), rtol=1e-9)


@pytest.mark.parametrize(
    "name",
    [
        "spow(y[t-1],0.5)",
        "apow(dy[t-2],1.5)",
        "y[t-1]*x[t-1]*apow(dy[t-2],1.5)",
        "deadzone(x[t-4],1500.0)^3",
        "backlash(x[t-4],0.25)",
        "y[t-1]*abs(dy[t-1])",
        "abs(y[t-2])*dy[t-2]",
        "sign(y[t-3])",
        "y[t-4]^2*dy[t-1]",
        "boucwen(y[t-2],0.05)",
        "boucwen(y[t-2],0.05,-1.375)",
        "boucwen(y[t-1],0.25)*x[t-1]",
    ],
)
def test_new_term_syntax_round_trips(name: str) -> None:
    term = Term.parse(name)
    assert term.name == name
    assert Term.parse(term.name) == term


NEW_FACTORS = [
    "y[t-1]",
    "y[t-2]",
    "spow(y[t-1],0.5)",
    "apow(dy[t-1],1.5)",
    "y[t-1]*abs(dy[t-1])",
    "abs(y[t-2])*dy[t-2]",
    "sign(y[t-1])",
    "deadzone(x[t-1],0.3)",
    "backlash(x[t-2],0.2)",
    "boucwen(y[t-2],0.4,0.5)",
    "x[t-1]",
]


def reference_free_run(theta, x, y0, limits, saturation) -> np.ndarray:
    """The recursion of NEW_FACTORS written out in Python; backlash by its own play loop
    started at 0, the input being 0 before the record (as the free run sees it); the Bouc–Wen
    variable (level 0.4, shape 0.5) from 0 at the first sample, driven by the simulated output,
    each step by :func:`bouc_wen_step` (which the test below holds to the differential equation)."""
    played, previous = [], 0.0
    for value in x:
        previous = min(max(previous, value - 0.2), value + 0.2)
        played.append(previous)
    state = list(y0)
    reported = list(y0)
    z = [0.0]
    for t in range(1, len(y0)):
        z.append(bouc_wen_step(z[-1], state[t] - state[t - 1], 0.4, 0.5))
    for t in range(len(y0), len(x)):
        s1, s2, s3 = state[t - 1], state[t - 2], state[t - 3]
        d1, d2 = s1 - s2, s2 - s3
        x1 = x[t - 1]
        phi = [
            s1,
            s2,
            np.sign(s1) * abs(s1) ** 0.5,
            abs(d1) ** 1.5,
            s1 * abs(d1),
            abs(s2) * d2,
            np.sign(s1),
            x1 - min(max(x1, -0.3), 0.3),
            played[t - 2],
            z[t - 2],
            x1,
        ]
        value = float(np.dot(theta, phi))
        clipped = min(max(value, limits[0]), limits[1])
        state.append(clipped if saturation == "state" else value)
        reported.append(clipped)
        z.append(bouc_wen_step(z[-1], state[t] - state[t - 1], 0.4, 0.5))
    return np.array(reported)


@pytest.mark.parametrize("saturation", ["state", "sensor"])
def test_free_run_with_the_new_factors_equals_a_python_recursion(saturation) -> None:
    rng = np.random.default_rng(4)
    x = rng.normal(size=400)
    theta = np.array([1.2, -0.5, 0.02, 0.01, -0.02, 0.01, 0.01, 0.1, 0.1, -0.1, 0.3])
    terms = parse_terms(NEW_FACTORS)
    limits = (-0.8, 0.6)
    model = NARX(terms, theta, np.zeros((11, 11)), output_limits=limits, saturation=saturation)
    y0 = np.array([0.1, -0.2, 0.3])
    simulated = model.simulate(x, y0)
    expected = reference_free_run(theta, x, y0, limits, saturation)
    assert np.any(simulated == limits[1]) and np.any(simulated == limits[0])  # the limits act
    np.testing.assert_allclose(simulated, expected, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("shape", [1.0, 0.3, 2.0, -1.5, -3.0])
def test_the_bouc_wen_variable_solves_its_differential_equation_over_steps_larger_than_its_level(shape):
    """dz = dy − β|dy|·z − γ·dy·|z| integrated by forward differences over a thousand substeps of
    each sample's step (y moving linearly between samples): the variable advanced a whole step at
    once agrees with it to the substeps' error, for every class of shape, on a series whose steps
    reach four times the level (where a forward difference over a whole step overshoots it)."""
    level, substeps = 0.5, 1000
    y = np.random.default_rng(6).normal(size=300) * level
    assert np.max(np.abs(np.diff(y))) > 4 * level
    beta = 0.5 / level
    gamma = shape * beta
    z, integrated = 0.0, [0.0]
    for step in np.diff(y) / substeps:
        for _ in range(substeps):
            z += step - beta * abs(step) * z - gamma * step * abs(z)
        integrated.append(z)
    exact = bouc_wen(y, level, shape)
    # The substeps' error grows with z where it runs away (shape −3: half of this bound).
    assert np.max(np.abs(exact - integrated)) < 1e-2 * np.max(np.abs(integrated))


def test_output_limits_are_the_plateaus() -> None:
    y = np.sin(np.linspace(0, 20, 2000)) * 1.3
    assert output_limits(y) is None  # a smooth signal touches its extremes once
    assert output_limits(np.clip(y, -2.0, 1.0)) == (-np.inf, 1.0)
    assert output_limits(np.clip(y, -0.5, 1.0)) == (-0.5, 1.0)


def test_a_saturating_model_document_round_trips_and_old_documents_read_as_none() -> None:
    record = simulate(
        Scenario(disturbance_std=200.0, effects=Effects.parse(["sensor_range=0.08"])), 4000, seed=2
    )
    limits = output_limits(record.y)
    model = fit_narx([(record.x, record.y)], EXACT_TERMS, output_limits=limits, saturation="sensor")
    document = model.to_document()
    assert document["output_limits"] == [-0.08, 0.08] and document["saturation"] == "sensor"
    again = NARX.from_document(document)
    assert again.output_limits == limits and again.saturation == "sensor"
    np.testing.assert_array_equal(again.simulate(record.x, record.y), model.simulate(record.x, record.y))
    plain = fit_narx([(record.x, record.y)], EXACT_TERMS).to_document()
    assert "output_limits" not in plain and NARX.from_document(plain).output_limits is None
    with pytest.raises(InputError, match="low < high"):
        NARX.from_document(document | {"output_limits": [0.1, -0.1]})
    with pytest.raises(InputError, match="'state' or 'sensor'"):
        NARX.from_document(document | {"saturation": "valve"})


def test_a_sensor_fit_leaves_out_the_equations_clipping_corrupts() -> None:
    """On a clipped record with no disturbance, the equations clear of the plateaus are exact:
    the sensor-saturating fit recovers the exact NARX's coefficients, the plain fit does not."""
    record = simulate(Scenario(effects=Effects.parse(["sensor_range=0.08"])), 6000, seed=3)
    clean = simulate(Scenario(), 6000, seed=3)
    exact = fit_narx([(clean.x, clean.y)], EXACT_TERMS).theta
    limits = output_limits(record.y)
    sensor = fit_narx([(record.x, record.y)], EXACT_TERMS, output_limits=limits, saturation="sensor").theta
    plain = fit_narx([(record.x, record.y)], EXACT_TERMS).theta
    np.testing.assert_allclose(sensor, exact, rtol=1e-6)
    assert not np.allclose(plain, exact, rtol=1e-2)


def on_a_plateau(seed: int, disturbance: float) -> tuple[NARX, np.ndarray, np.ndarray, int]:
    """The rig's exact NARX as a sensor-saturating model, a 1600-sample record through a sensor
    clipping at ±0.08 m (``disturbance`` N of unmeasured force), and the first sample from 800 on
    that begins four readings on a plateau: where a held-out tail or check block may begin."""
    scenario = Scenario(disturbance_std=disturbance, effects=Effects.parse(["sensor_range=0.08"]))
    record = simulate(scenario, 1600, seed)
    limits = output_limits(record.y)
    assert limits is not None
    on = (record.y <= limits[0]) | (record.y >= limits[1])
    start = next(t for t in range(800, 1200) if on[t : t + 4].all())
    exact = replace(exact_narx(scenario.params), output_limits=limits, saturation="sensor")
    return exact, record.x, record.y, start


def test_a_sensor_models_free_run_starts_where_the_readings_are_the_systems_output() -> None:
    """A clipped reading is not the system's output: a free run started from four readings on a
    plateau starts from a state the rig was not in. With no disturbance the exact model run from
    the first readings clear of the plateau reproduces the rest of the record; started on the
    plateau, its wrong start rings through the lightly damped rig's whole run."""
    exact, x, y, start = on_a_plateau(seed=3, disturbance=0.0)
    part = (x[start : start + 400], y[start : start + 400], start)
    assert run_start(part[1], exact.max_lag, exact.output_limits) > exact.max_lag
    assert free_run_rms(exact, [part]) < 1e-9 * np.std(y)
    from_the_plateau = exact.simulate(part[0], part[1][:4])[4:] - part[1][4:]
    assert np.sqrt(np.mean(from_the_plateau**2)) > 0.1 * np.std(y)


def test_validation_runs_a_sensors_model_free_from_the_readings_clear_of_its_limits() -> None:
    """The held-out validation's free run (the bench's and `narxwatch select`'s) starts as the
    loop's do: on a record that begins on the plateau the exact model, started clear of it,
    reproduces the rest of the record and is scored over the samples it predicts from there."""
    exact, x, y, start = on_a_plateau(seed=3, disturbance=0.0)
    part_x, part_y = x[start : start + 400], y[start : start + 400]
    free_run = validate(exact, [(part_x, part_y)], t0=start).free_run
    assert free_run.rms < 1e-9 * np.std(y)
    assert free_run.samples == part_y.size - run_start(part_y, exact.max_lag, exact.output_limits)


def test_the_tails_tell_a_clipping_sensors_model_with_the_springs_dynamics_from_one_without() -> None:
    """The rig's cubic spring reaches y through mass 1's dynamics, as y[t-2]³, y[t-3]³, y[t-4]³
    whose coefficients nearly cancel; a model holding only their sum, as y[t-1]³, is its static
    part. On a tail that begins on a plateau (200 N of unmeasured force), both run from there
    made the first figure lower and the comparison could not tell them apart, and the loop,
    judging its rounds and pruning so, returned the static part and ran free over another
    record ten times as far off as the rig's model. Both run from the first readings clear of
    the plateau, the exact model is the better beyond the comparison's uncertainty."""
    exact, x, y, start = on_a_plateau(seed=3, disturbance=200.0)
    theta = exact.theta
    static = NARX(
        parse_terms(["y[t-1]", "y[t-2]", "y[t-3]", "y[t-4]", "y[t-1]^3", "x[t-4]"]),
        np.concatenate((theta[:4], [theta[4:7].sum()], theta[7:])),
        np.zeros((6, 6)),
        output_limits=exact.output_limits,
        saturation="sensor",
    )
    tail = (x[start : start + 400], y[start : start + 400], start)
    held_out = compare_on_tails(static, exact, [tail], heads=[(x[:start], y[:start])])
    assert held_out.better, held_out
    assert held_out.refined_rms < 0.2 * held_out.start_rms


def wiener_hammerstein(seed: int, n: int, hammerstein: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """y = G2(f(G1 x)) with f(v) = v + 0.6·v² − 0.25·v³ (asymmetric), G1 = 0.5q⁻¹/(1 − 0.5q⁻¹)
    (infinite impulse response: a combination of the model's three input lags holds it only
    nearly), G2 = q⁻¹/(1 − 1.2q⁻¹ + 0.5q⁻²), and white measurement noise at 5 % of the output's
    std. ``hammerstein`` leaves G1 out: the same f before the dynamics, G2 with a second lag."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(n)
    v = x if hammerstein else signal.lfilter([0.0, 0.5], [1.0, -0.5], x)
    w = v + 0.6 * v**2 - 0.25 * v**3
    clean = signal.lfilter([0.0, 1.0, 0.5] if hammerstein else [0.0, 1.0], [1.0, -1.2, 0.5], w)
    return x, clean + 0.05 * np.std(clean) * rng.standard_normal(n)


def test_a_static_nonlinearity_between_two_filters_is_named_first_and_the_free_run_halves() -> None:
    """From a linear (2, 3) model on two estimation records (the combination is sought on the
    first, its regressor built on both): the filtered input nonlinearity is named first, and the
    held-out free-run RMS falls to less than half of the declared model's and of the best the
    linear structure does with output-error parameters."""
    x, y = wiener_hammerstein(seed=1, n=6000)
    declared = linear_terms(2, 3)
    estimation = [(x[:2000], y[:2000]), (x[2000:4000], y[2000:4000])]
    report = refine_records(estimation, [(x[4000:], y[4000:])], declared)
    names = [e.name for e in report.refinement.effects_added]
    assert names and names[0] == "filtered_input_nonlinearity", names
    first = parse_terms(report.refinement.effects_added[0].terms)
    assert first and all({f.signal for f in t.factors} == {"x"} and t.degree in (2, 3) for t in first)
    assert report.after.free_run_rms <= report.before.free_run_rms / 2, (report.before, report.after)
    linear = fit_output_error(fit_narx(estimation, declared), estimation, SETTLED_EVALUATIONS).model
    assert report.after.free_run_rms <= assess(linear, x[4000:], y[4000:]).free_run_rms / 2


def test_the_combination_of_input_lags_is_found() -> None:
    """A residual that is exactly a·u² + b·u³ of u = x[t-1] − 0.5·x[t-2] + 0.25·x[t-3], beside a
    linear model: the family's regressor is that function (up to scale), and its span holds it."""
    rng = np.random.default_rng(4)
    x = rng.standard_normal(6000)
    y = signal.lfilter([0.0, 1.0], [1.0, -0.5], x)
    terms = linear_terms(1, 3)
    lag = 3
    u = x[lag - 1 : -1] - 0.5 * x[lag - 2 : -2] + 0.25 * x[lag - 3 : -3]
    truth = 0.4 * u**2 - 0.1 * u**3
    Phi, _ = regressor_matrix(list(terms), x, y, lag)
    residual = truth - Phi @ np.linalg.lstsq(Phi, truth, rcond=None)[0]  # off the model, as a residual is
    effect = next(e for e in candidate_effects(terms) if e.name == "filtered_input_nonlinearity")
    spanning, column = effect.combine([(x, y)], residual, terms, lag)
    assert abs(np.corrcoef(column, truth)[0, 1]) > 1 - 1e-6
    span, _ = regressor_matrix(list(terms + spanning), x, y, lag)
    left = truth - span @ np.linalg.lstsq(span, truth, rcond=None)[0]
    assert np.linalg.norm(left) < 1e-8 * np.linalg.norm(truth)


def test_a_bouc_wen_oscillator_is_named_hysteresis_with_nothing_declared() -> None:
    """A single-DOF oscillator with a Bouc–Wen restoring force whose variable stiffens as the
    displacement moves on (γ = −1.5·β, the class of Noël and Schoukens' benchmark), sampled at
    500 Hz where a step of y reaches the level 1/(2β), and nothing declared: the loop names
    hysteresis first, with that level and shape, and the free run falls to a quarter. (A family
    of β = γ alone, discretised by forward differences, was not offered on this record; the loop
    named a cubic spring and five more, the free run falling to 0.4.)"""
    oscillator = BoucWenOscillator()
    x, y = oscillator.record(4000, force_std=8.0, noise_std=3e-6, seed=1)
    report = refine_record(x, y, None, [(0, 3000)], (3000, 4000))
    added = report.refinement.effects_added
    assert added and added[0].name == "hysteresis", [e.name for e in added]
    factor = Term.parse(added[0].terms[0]).factors[0]
    assert factor.parameter == pytest.approx(0.5 / oscillator.beta, rel=0.1)
    assert factor.shape == pytest.approx(oscillator.gamma / oscillator.beta, abs=0.15)
    assert report.after.free_run_rms <= report.before.free_run_rms / 4, (report.before, report.after)


def test_the_rigs_hysteresis_is_named_first_on_its_free_run_with_nothing_declared() -> None:
    """The rig with a Bouc–Wen spring on mass 2 (``hysteresis2``, saturating at 5 cm), 4000
    samples, nothing declared. The Bouc–Wen variable is a smooth state that the residual's own
    recent past predicts one step ahead, so moving-average noise led the one-step order and took
    the first rounds, and the held-out tails withdrew what followed. Judged on its free run,
    hysteresis is named first, at a level near the element's, and the model runs free over a
    record from another seed at a fraction of the start's error."""
    scenario = Scenario(disturbance_std=200.0, effects=Effects.parse(["hysteresis2=3e4"]))
    record, other = simulate(scenario, 4000, seed=4), simulate(scenario, 4000, seed=5)
    report = refine_records([(record.x, record.y)], [(other.x, other.y)], None)
    refinement = report.refinement
    added = refinement.effects_added
    assert added and added[0].name == "hysteresis", [e.name for e in added]
    assert refinement.kept[0].criterion == "simulation"
    factor = Term.parse(added[0].terms[0]).factors[0]
    level = 2 * factor.parameter / (1 + factor.shape)  # where z saturates
    assert level == pytest.approx(1 / (BOUC_WEN_BETA + BOUC_WEN_GAMMA), rel=0.2)
    assert report.after.free_run_rms <= report.before.free_run_rms / 2, (report.before, report.after)


def test_the_held_out_tails_run_the_rigs_hysteresis_over_the_records_head() -> None:
    """The rig with a Bouc–Wen spring on mass 2 (``hysteresis2``), 1600 samples, nothing declared
    (seed 8012, held out once and spent): the loop adds the rig's cubic spring, then the
    hysteresis at about the element's level. The held-out tails withdrew both: each free run
    over them started the Bouc–Wen variable at rest at the tail's first sample, where the
    measured head puts it anywhere within its level, and over 320 samples the output did not
    move far enough for it to forget that start; the model ran free there twice as far off as
    the start. Run over the measured head, as the lags read the tail's first outputs, the
    variable starts where the record has it: the model is kept, and runs free over another
    seed's record at a fraction of the start's error."""
    scenario = Scenario(disturbance_std=200.0, effects=Effects.parse(["hysteresis2=3e4"]))
    record, other = simulate(scenario, 1600, seed=8012), simulate(scenario, 4000, seed=58012)
    report = refine_records([(record.x, record.y)], [(other.x, other.y)], None)
    refinement = report.refinement
    assert [e.name for e in refinement.effects_added] == ["cubic_stiffness", "hysteresis"]
    assert refinement.held_out is not None and refinement.held_out.kept
    factor = Term.parse(refinement.effects_added[1].terms[0]).factors[0]
    level = 2 * factor.parameter / (1 + factor.shape)  # where z saturates
    assert level == pytest.approx(1 / (BOUC_WEN_BETA + BOUC_WEN_GAMMA), rel=0.2)
    assert report.after.free_run_rms <= report.before.free_run_rms / 3, (report.before, report.after)


def test_a_static_nonlinearity_before_the_dynamics_is_the_input_nonlinearity() -> None:
    """Hammerstein: the same f of the unfiltered input before G2 with two numerator lags, f at two
    lags, which no single combination's powers hold: the per-lag input nonlinearity is named
    first, not the filtered one."""
    x, y = wiener_hammerstein(seed=1, n=6000, hammerstein=True)
    report = refine_record(x, y, linear_terms(2, 3), [(0, 4000)], (4000, 6000))
    names = [e.name for e in report.refinement.effects_added]
    assert names and names[0] == "input_nonlinearity", names


def test_a_familys_information_criterion_counts_the_terms_it_adds() -> None:
    """The filtered input nonlinearity is tested with one regressor, the combination's powers, but
    adds the monomials spanning them, which the model then estimates freely: the fall of BIC
    charges ln n for each of those terms, as for the per-lag family's. Counting regressors
    instead ranked the two within 0.02 of each other on Silverbox, and which came first
    depended on the last bits of an extended least-squares fit."""
    x, y = wiener_hammerstein(seed=1, n=8000, hammerstein=True)
    terms = linear_terms(2, 3)
    effects = candidate_effects(terms)
    scores = {s.name: s for s in score_effects([(x, y)], terms, 0, effects, 0.01).scores}
    filtered = scores["filtered_input_nonlinearity"]
    assert filtered.significant and len(filtered.f_statistics) == 1 and len(filtered.terms) > 10
    n = len(y) - max([max_lag(terms)] + [max_lag(e.terms) for e in effects if e.terms])
    for score in scores.values():
        if score.significant:
            expected = n * np.log1p(-score.explained) + len(score.terms) * np.log(n)
            assert score.bic_change == pytest.approx(expected, rel=1e-12), score.name


def test_a_combination_is_not_sought_where_the_first_record_leaves_nothing_to_explain() -> None:
    """The search reads the first record: a residual that is zero there (as a saturating model's
    is on its limits) gives no terms on any record, rather than a search on 0/0."""
    rng = np.random.default_rng(5)
    records = [(rng.standard_normal(3000), rng.standard_normal(3000)) for _ in range(2)]
    terms = linear_terms(1, 3)
    lag = 4  # the unmeasured coordinate's cubics reach y[t-4]
    residual = np.concatenate([np.zeros(3000 - lag), rng.standard_normal(3000 - lag)])
    combined = [effect for effect in candidate_effects(terms) if effect.kind == "combined"]
    # The offset of a linear model without a constant is sought as the cube it shows through.
    assert {effect.name for effect in combined} == {
        "unmeasured_nonlinearity",
        "filtered_input_nonlinearity",
        "offset",
    }
    for effect in combined:
        spanning, column = effect.combine(records, residual, terms, lag)
        assert spanning == () and column.shape == residual.shape and not column.any(), effect.name


def test_a_combination_spans_only_the_monomials_the_model_does_not_span_already() -> None:
    """A combined family adds the monomials the model does not span already: with some of the
    unmeasured cube's among the model's terms, the others; with all of them, none (the family
    is not offered), however small what rounding leaves of them off the model. Judged against
    the largest remainder, the remainders were all taken for independent and the family put the
    model's own terms into it again, a structure no least squares can fit."""
    rng = np.random.default_rng(6)
    x = rng.standard_normal(3000)
    y = signal.lfilter([0.0, 1.0], [1.0, -1.5, 0.7], x)
    linear = linear_terms(4, 4)
    effect = next(e for e in candidate_effects(linear) if e.name == "unmeasured_nonlinearity")
    cubics = effect.terms
    lag = max_lag(linear + cubics)
    residual = rng.standard_normal(len(y) - lag)

    def spanning(terms: tuple[Term, ...]) -> tuple[Term, ...]:
        return effect.combine([(x, y)], residual, terms, lag)[0]

    assert spanning(linear) == cubics
    assert spanning(linear + cubics[:5]) == cubics[5:]
    assert spanning(linear + cubics) == ()


def test_a_stiffness_law_at_its_ranges_end_below_the_cubic_is_not_offered() -> None:
    """The power law of y is searched on exponents up to 2.6, the cubic spring's y³ just above: a
    residual that asks for the cubic finds the law's best exponent at the range's end, no
    estimate of a law of its own, and the family offers nothing; a residual of |y|^1.5·sign y
    (a Hertzian contact) gets its exponent."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=3000)
    y = signal.lfilter([0.0, 1.0], [1.0, -1.5, 0.7], x)
    declared = linear_terms(2, 2, 1)
    (law,) = [effect for effect in candidate_effects(declared) if effect.name == "power_law_stiffness"]
    assert law.find is not None
    lag = 4
    before = y[lag - 1 : -1]  # y[t-1] on the rows t = lag … N−1
    noise = 0.01 * rng.normal(size=before.size)
    cubic, contact = before**3, np.abs(before) ** 1.5 * np.sign(before)
    assert law.find(SearchInput(x, y, cubic / np.std(cubic) + noise, declared, lag)) == ()
    found = law.find(SearchInput(x, y, contact / np.std(contact) + noise, declared, lag))
    assert found and found[0].factors[0].parameter == pytest.approx(1.5, abs=0.02), found


@pytest.mark.parametrize(
    ("spec", "integer"),
    [
        ("coulomb2=300", "coulomb_friction"),
        ("quadratic_damping2=2000", "quadratic_damping"),
        ("power_damping2=1000", None),
    ],
)
def test_a_damping_law_at_its_ranges_end_that_an_integer_law_beyond_explains_better_is_not_offered(
    spec: str, integer: str | None
) -> None:
    """The rig with Coulomb friction (a law of exponent 0), quadratic damping (2) or an orifice's
    damping (½) on mass 2, 600 samples, the linear start's one-step residual. The damping law's
    exponent is searched between the integer laws, 0.2 to 1.8: friction and quadratic damping
    put its best at the range's end, where the integer law beyond it explains the residual
    better beyond the exponent's uncertainty (the likelihood-ratio test of the exponent,
    computed here by least squares on the start's regressors and the law's), and the family
    offers nothing: the integer law's own family names the effect. The orifice's law is told
    from every integer law, and offered at its exponent."""
    record = simulate(Scenario(disturbance_std=200.0, effects=Effects.parse([spec])), 600, seed=1)
    x, y = record.x, record.y
    declared, lag = linear_terms(4, 4, 1), 5
    Phi, target = regressor_matrix(list(declared), x, y, lag)
    residual = target - Phi @ linalg.lstsq(Phi, target)[0]
    (law,) = [effect for effect in candidate_effects(declared) if effect.name == "power_law_damping"]
    assert law.find is not None
    velocity, _ = regressor_matrix([Term((Factor("dy", k),)) for k in range(1, 5)], x, y, lag)

    def left(p: float) -> float:  # the residual sum of squares with the law at exponent p beside the start
        columns = np.hstack([Phi, np.sign(velocity) * np.abs(velocity) ** p])
        columns /= np.linalg.norm(columns, axis=0)
        return float(np.sum((target - columns @ linalg.lstsq(columns, target)[0]) ** 2))

    bound = stats.chi2.ppf(1 - EXPONENT_ALPHA, 1)
    found = law.find(SearchInput(x, y, residual, declared, lag))
    integers = {"coulomb_friction": 0.0, "quadratic_damping": 2.0, "cubic_damping": 3.0}
    if integer is None:
        assert found, spec
        exponent = found[0].factors[0].parameter
        assert exponent == pytest.approx(0.5, abs=0.03)
        assert all(target.size * np.log(left(k) / left(exponent)) > bound for k in integers.values())
    else:
        assert found == (), found
        end = 0.2 if integers[integer] < 1 else 1.8
        assert target.size * np.log(left(end) / left(integers[integer])) > bound


def test_integer_powers_are_the_products_a_factor_computes_and_pow_to_its_rounding() -> None:
    """The combination searches take u² and u³ by repeated products, as a term's factor does
    (numpy's pow with an array of exponents took three quarters of their time): the same
    numbers as the factor's, and pow's to within the rounding of two products."""
    u = np.random.default_rng(3).standard_normal(10_000) * np.geomspace(1e-3, 1e3, 10_000)
    degrees = np.array([0, 1, 2, 3])

    powers = integer_powers(u, degrees)

    assert np.array_equal(powers[:, 0], np.ones_like(u))
    for column, degree in zip(powers.T[1:], degrees[1:], strict=True):
        factor = Factor("y", 1, int(degree))
        assert np.array_equal(column, factor.values(lambda k: u, lambda k: u, np.arange(u.size)))
    for column, degree in zip(powers.T, degrees, strict=True):
        np.testing.assert_allclose(column, u**degree, rtol=2.5 * np.finfo(float).eps, atol=0)


def test_a_search_reads_the_basis_of_its_own_model_over_its_own_rows() -> None:
    """The searched families of a round share the model's basis over the rows they search (it is
    kept from one search to the next): each search, after one on another model or another record,
    reads a basis of its own model's regressors over its own rows (against scipy's QR of them),
    which no search can write to."""
    rng = np.random.default_rng(4)
    first, second = (rng.standard_normal((2, 3000)) for _ in range(2))
    linear, grown = linear_terms(2, 2), (*linear_terms(2, 2), *parse_terms(["y[t-1]^3"]))
    lag = 2
    for (x, y), terms in [(first, linear), (first, grown), (second, grown), (first, linear)]:
        residual = rng.standard_normal(len(y) - lag)
        *_, basis = _search_part(x, y, residual, terms, lag)
        Phi, _ = regressor_matrix(list(terms), x, y, lag)
        reference = linalg.qr(Phi, mode="economic")[0]
        np.testing.assert_allclose(np.abs(basis.T @ reference), np.eye(len(terms)), atol=1e-10)
        with pytest.raises(ValueError, match="read-only"):
            basis[0, 0] = 0.0


def test_an_output_reads_as_a_magnitude_where_it_never_goes_below_zero_and_comes_down_to_it() -> None:
    _, readings, speed = rectified_drive(seed=1)
    assert reads_magnitude(readings) and reads_magnitude(readings - 0.022)  # a counter's offset at rest
    assert not reads_magnitude(speed)  # signed: it crosses zero
    assert not reads_magnitude(readings + 1.0)  # a level far from zero never shows the fold
    assert not reads_magnitude(readings - 0.1 * np.ptp(readings))  # below zero beyond an offset


def test_a_rectified_model_reports_the_magnitude_of_its_recursion_and_its_document_round_trips() -> None:
    x, y, _ = rectified_drive(seed=2, n=300)
    terms = ("y[t-1]", "y[t-2]", "x[t-1]", "1")
    theta = np.array([1.5, -0.7, 0.4, -0.05])
    model = replace(fit_narx([(x, y)], terms), theta=theta, rectified=True)
    z = np.zeros_like(y)
    z[:2] = y[:2]  # the readings taken as the signed output: the positive branch
    for t in range(2, len(y)):
        z[t] = 1.5 * z[t - 1] - 0.7 * z[t - 2] + 0.4 * x[t - 1] - 0.05
    assert np.min(z) < -0.5  # the recursion turns sign; the model reports its magnitude
    np.testing.assert_allclose(model.simulate(x, y), np.abs(z), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(model.predict(x, y), np.abs(theta[:3] @ [y[1:-1], y[:-2], x[1:-1]] + theta[3]))
    document = model.to_document()
    assert document["rectified"] is True and NARX.from_document(document).rectified
    plain = replace(model, rectified=False).to_document()
    assert "rectified" not in plain and not NARX.from_document(plain).rectified
    with pytest.raises(InputError, match="rectified is true or false"):
        NARX.from_document(document | {"rectified": "yes"})


def test_output_error_fits_the_recursion_under_a_sensor_blind_to_the_sign() -> None:
    """Least squares on the readings fits the folds, not the drive; output error on what the
    sensor reads, started from that fit, finds the signed recursion: on a fresh record its free
    run is within a few times the sensor's noise, the linear model's is at the readings' spread."""
    x, y, _ = rectified_drive(seed=3, n=1000)
    fresh_x, fresh_y, _ = rectified_drive(seed=4, n=500)
    start = fit_narx([(x, y)], linear_terms(3, 3, 1, constant=True))
    fits = {
        rectified: fit_output_error(replace(start, rectified=rectified), [(x, y)])
        for rectified in (False, True)
    }
    runs = {rectified: assess(fit.model, fresh_x, fresh_y, 4).free_run_rms for rectified, fit in fits.items()}
    assert runs[True] < 0.05 < 0.2 * np.std(fresh_y) < runs[False], runs


def test_on_a_short_record_the_rectifier_is_taken_though_its_one_check_block_extrapolates() -> None:
    """The coupled drives' protocol on a simulated drive whose input sits 0.5 above zero, as the
    second record's does: 400 estimation samples, the free run scored over the last 100 from 4
    measured ones. On the one check block the rectified fit extrapolates (main refused it there
    and returned the linear start, 0.305); taken on the readings' shape, the refined model runs
    the test at a third of the start's error, and it passed the held-out tail's comparison."""
    x, y, _ = rectified_drive(seed=14, offset=0.5)
    report = refine_records([(x[:400], y[:400])], [(x[396:], y[396:])], None, initial=4)
    assert report.refinement.refined.rectified
    assert report.refinement.effects_added[0].name == "rectified_output"
    assert report.after.free_run_rms < report.before.free_run_rms / 2, (report.before, report.after)


def test_a_sensor_blind_to_the_sign_is_named_first_with_nothing_declared() -> None:
    """A drive read by a counter blind to the direction, nothing declared: the rectifier, from the
    orders chosen as the rectified model's (a linear model of the readings fits the folds with
    other orders), is named first, and the free run over a fresh stretch falls below a fifth (main:
    orders (2, 2, 1), nothing kept, 0.301 against the start's 0.389; here 0.050)."""
    x, y, _ = rectified_drive(seed=2, n=2500)
    report = refine_records([(x[:2000], y[:2000])], [(x[2000:], y[2000:])], None, initial=10)
    names = [e.name for e in report.refinement.effects_added]
    assert names and names[0] == "rectified_output", names
    assert report.refinement.refined.rectified
    assert report.after.free_run_rms < report.before.free_run_rms / 5, (report.before, report.after)
    # The report explains it: without the rectifier the model reads its recursion's signed output.
    rectifier = explain_refinement(report.refinement, x[2000:], y[2000:], initial=10).effects[0]
    assert rectifier.removal is not None and rectifier.removal > 0.5, rectifier


# The linear structure's clean record (the rig with its cubic spring taken out, 800 N of unmeasured
# force, as bench.planted's clean records), cut to a 1600-sample record's head as the loop cuts it.
LINEAR_RIG = Scenario(params=PhysicalParameters(k3=0.0), disturbance_std=800.0)
HEAD = 1280


@pytest.mark.parametrize(
    ("name", "seed"), [("filtered_input_nonlinearity", 76), ("unmeasured_nonlinearity", 92)]
)
def test_a_combined_familys_test_counts_the_combination_its_search_chose(name: str, seed: int) -> None:
    """On a clean record of a linear structure a combined family has nothing to find, yet its one
    regressor is the best of a whole family of combinations, chosen on the residual its test
    reads: tested as one free column it passed the round's level on these records (and on 20 of
    300 such records, where the level allows one in 4000). Its test counts the combination's
    parameters, as a searched exponent's is counted, and it does not pass. The family's regressor
    refitted by least squares beside the model, independently of the scoring, shows what the
    single column's test said."""
    record = simulate(LINEAR_RIG, 1600, seed=seed)
    x, y = record.x[:HEAD], record.y[:HEAD]
    terms = linear_terms(4, 4, 1)
    effects = candidate_effects(terms)
    scores = score_effects([(x, y)], terms, 0, effects, DEFAULT_ALPHA)
    assert not next(s for s in scores.scores if s.name == name).significant
    effect = next(e for e in effects if e.name == name)
    assert effect.searched == combination_parameters(range(1, 5), (2, 3) if "filtered" in name else (3,))
    lag = max([max_lag(terms)] + [max_lag(e.terms) for e in effects if e.terms])
    Phi, target = regressor_matrix(list(terms), x, y, lag)[0], y[lag:]
    residual = target - Phi @ np.linalg.lstsq(Phi, target, rcond=None)[0]
    _, column = effect.combine([(x, y)], residual, terms, lag)
    both = np.column_stack([Phi, column])
    after = target - both @ np.linalg.lstsq(both, target, rcond=None)[0]
    fall, dof = residual @ residual - after @ after, len(target) - both.shape[1]
    one_column = stats.f.sf(fall / (after @ after / dof), 1, dof)
    counted = stats.f.sf(
        fall / (1 + effect.searched) / (after @ after / (dof - effect.searched)),
        1 + effect.searched,
        dof - effect.searched,
    )
    assert one_column < scores.level < counted, (one_column, scores.level, counted)
