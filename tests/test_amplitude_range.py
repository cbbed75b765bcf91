"""A model's amplitude range (models.amplitude_range) against an independent computation: the
exact discrete model of the simulator's cubic spring, whose free run escapes at some multiple of
the amplitude it is driven at, and linear models, whose range has no limit."""

from __future__ import annotations

import numpy as np
import pytest

from models.amplitude_range import SCALES, AmplitudeRange, amplitude_range, amplitude_ranges, linear
from models.narx import NARX
from models.output_error import RESTLESS
from models.terms import parse_terms
from simulator.physics import PhysicalParameters
from simulator.simulate import Scenario, simulate
from simulator.theory import exact_coefficients, exact_narx

# A record of the rig at rest at its start, its force loud enough that its exact model escapes
# within the scales tried, and not so loud that the simulator refuses it.
RIG_FORCE, RIG_SEED, RIG_SAMPLES = 180e3, 3, 1000


def escaping(theta: np.ndarray, x: np.ndarray, y: np.ndarray, scales: np.ndarray) -> np.ndarray:
    """For each scale s, whether the exact model (simulator.theory's equation, written out here
    term by term) driven by s·x from s·y's first four samples leaves RESTLESS · s · max |y| or
    stops being finite: all scales run side by side."""
    a, cubic, b = theta[:4], theta[4:7], theta[7]
    run = np.zeros((scales.size, x.size))
    run[:, :4] = np.outer(scales, y[:4])
    drive = np.outer(scales, x)
    with np.errstate(over="ignore", invalid="ignore"):
        for t in range(4, x.size):
            previous = run[:, t - 4 : t][:, ::-1]  # y[t-1] … y[t-4]
            run[:, t] = previous @ a + previous[:, 1:] ** 3 @ cubic + b * drive[:, t - 4]
            run[~np.isfinite(run[:, t]), t] = np.inf
    bound = RESTLESS * scales * np.max(np.abs(y[4:]))
    return ~np.all(np.isfinite(run[:, 4:]), axis=1) | (np.max(np.abs(run[:, 4:]), axis=1) > bound)


def test_the_exact_cubic_spring_models_range_ends_where_its_direct_simulation_escapes():
    """The rig's exact NARX, driven by its own record's force scaled up: a direct simulation of
    its equation over a fine grid of scales escapes from one scale on (and at every one beyond,
    on this record), and the range reports the largest scale tried below that one and the first
    at or above it. A polynomial model with a hardening spring's cube has a finite range: the
    true model as much as a refined one."""
    params = PhysicalParameters()
    record = simulate(Scenario(excitation_std=RIG_FORCE, burn_in=0), RIG_SAMPLES, seed=RIG_SEED)
    grid = np.round(np.arange(1.0, 3.2001, 0.01), 2)
    escapes = escaping(exact_coefficients(params), record.x, record.y, grid)
    assert escapes.any() and not escapes[0]
    first = int(np.argmax(escapes))
    assert escapes[first:].all()  # one escape scale: below it bounded, from it on escaping
    escape = grid[first]
    found = amplitude_range(exact_narx(params), [(record.x, record.y)])
    assert found.bounded_to == max(s for s in SCALES if s < escape)
    assert found.diverges_at == min(s for s in SCALES if s >= escape)
    assert found.to_dict() == {
        "bounded_to": found.bounded_to,
        "diverges_at": found.diverges_at,
        "description": f"bounded for inputs up to {found.bounded_to:g}× the estimation records' amplitude, "
        f"diverging at {found.diverges_at:g}×",
    }


def test_the_range_is_told_on_the_scales_given_in_increasing_order():
    """The same record on scales given out of order, 2.5, 1 and 1.5: the direct simulation stays
    bounded at 1 and 1.5 and escapes at 2.5, and so does the range."""
    params = PhysicalParameters()
    record = simulate(Scenario(excitation_std=RIG_FORCE, burn_in=0), RIG_SAMPLES, seed=RIG_SEED)
    escapes = escaping(exact_coefficients(params), record.x, record.y, np.array([1.0, 1.5, 2.5]))
    assert list(escapes) == [False, False, True]
    found = amplitude_range(exact_narx(params), [(record.x, record.y)], (2.5, 1.0, 1.5))
    assert found == AmplitudeRange(1.5, 2.5)


def test_a_stable_linear_models_range_has_no_limit():
    """An ARX model with an offset: its free run at scale s is s times the input's part plus the
    offset's, so bounded at the records' amplitude it is bounded at any. The range says no limit
    (inf; None in JSON), and a direct run at a hundred times the input, beyond every scale tried,
    stays within the bound."""
    model = NARX(
        parse_terms(["y[t-1]", "y[t-2]", "x[t-1]", "1"]), np.array([1.5, -0.7, 0.5, 0.02]), np.zeros((4, 4))
    )
    x = np.random.default_rng(4).standard_normal(800)
    y = model.simulate(x, np.zeros(2))
    assert linear(model)
    found = amplitude_range(model, [(x, y)])
    assert found == AmplitudeRange(np.inf, None) and not found.limited
    assert found.to_dict() == {"bounded_to": None, "diverges_at": None, "description": found.describe()}
    assert "any amplitude" in found.describe()
    loud = model.simulate(100 * x, 100 * y)[2:]
    assert np.max(np.abs(loud)) <= RESTLESS * 100 * np.max(np.abs(y[2:]))


def test_an_unstable_linear_model_diverges_at_the_records_own_amplitude():
    """A root outside the unit circle: the free run diverges at scale 1 already, and no linearity
    argument lifts that: the range is zero, diverging at 1."""
    model = NARX(parse_terms(["y[t-1]", "x[t-1]"]), np.array([1.05, 1.0]), np.zeros((2, 2)))
    x = np.random.default_rng(5).standard_normal(600)
    y = NARX(model.terms, np.array([0.5, 1.0]), np.zeros((2, 2))).simulate(x, np.zeros(1))
    found = amplitude_range(model, [(x, y)])
    assert found == AmplitudeRange(0.0, 1.0)
    assert found.describe() == "diverging at the estimation records' own amplitude"


def test_a_refinements_ranges_say_when_the_refined_models_is_the_narrower():
    """The linear start and the exact cubic model on the rig's record: the refined range is the
    narrower, and its scales are those tried."""
    params = PhysicalParameters()
    record = simulate(Scenario(excitation_std=RIG_FORCE, burn_in=0), RIG_SAMPLES, seed=RIG_SEED)
    start = NARX(
        parse_terms(["y[t-1]", "y[t-2]", "y[t-3]", "y[t-4]", "x[t-4]"]),
        exact_coefficients(params)[[0, 1, 2, 3, 7]],
        np.zeros((5, 5)),
    )
    ranges = amplitude_ranges(start, exact_narx(params), [(record.x, record.y)])
    assert ranges.narrower and not ranges.declared.limited and ranges.refined.limited
    assert ranges.to_dict()["scales"] == list(SCALES)
    assert ranges.to_dict()["declared"]["bounded_to"] is None


@pytest.mark.parametrize("terms", [["y[t-1]^3", "x[t-1]"], ["abs(y[t-1])", "x[t-1]"], ["y[t-1]*x[t-1]"]])
def test_a_term_of_degree_above_one_or_a_function_is_not_linear(terms: list[str]):
    model = NARX(parse_terms(terms), np.zeros(len(terms)), np.zeros((len(terms), len(terms))))
    assert not linear(model)
