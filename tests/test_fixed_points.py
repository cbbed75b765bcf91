"""A model's fixed points (models/fixed_points.py) against the roots of its static characteristic,
and the refinement loop refusing a model that comes to rest beyond the outputs its records
measured, where the start does not."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from models.fixed_points import LEVELS, beyond_the_records, fixed_points
from models.narx import NARX, fit_narx
from models.refinement import refine_records
from simulator.simulate import Effects, Scenario, simulate

A1, A2, GAIN, CONSTANT = 1.2, -0.5, 0.3, 0.01


def _model(terms: list[str], theta: list[float], seed: int = 0) -> NARX:
    """A model over ``terms`` with parameters ``theta`` (fitted first only to have its shape)."""
    rng = np.random.default_rng(seed)
    x, y = rng.standard_normal(400), rng.standard_normal(400)
    return replace(fit_narx([(x, y)], terms), theta=np.array(theta, dtype=np.float64))


def _real_roots(coefficients: list[float], low: float, high: float) -> np.ndarray:
    roots = np.roots(coefficients)
    real = np.sort(roots[np.abs(roots.imag) < 1e-9].real)
    return real[(real > low) & (real < high)]


@pytest.mark.parametrize(("square", "cube"), [(0.6, -1.0), (-0.9, 0.5), (0.0, -0.4)])
def test_the_fixed_points_of_a_polynomial_model_are_the_real_roots_of_its_static_characteristic(square, cube):
    """y[t] = a1·y[t−1] + a2·y[t−2] + b·x[t−1] + c + q·y[t−1]² + k·y[t−2]³, with velocity terms,
    Coulomb friction and a sinusoid of time that vanish or average out at rest: with the input
    held at u, its fixed points are the real roots of k·v³ + q·v² + (a1 + a2 − 1)·v + b·u + c."""
    terms = [
        "y[t-1]",
        "y[t-2]",
        "x[t-1]",
        "1",
        "y[t-1]^2",
        "y[t-2]^3",
        "dy[t-1]*abs(dy[t-1])",
        "sign(dy[t-1])",
        "sin(2pi*0.01*t)",
    ]
    model = _model(terms, [A1, A2, GAIN, CONSTANT, square, cube, 0.7, 0.2, 0.5])
    level, low, high = 0.4, -4.0, 4.0
    expected = _real_roots([cube, square, A1 + A2 - 1, GAIN * level + CONSTANT], low, high)
    found = fixed_points(model, level, low, high)
    assert found.size == expected.size >= 1
    np.testing.assert_allclose(found, expected, atol=(high - low) / (LEVELS - 1))


def test_a_softening_cube_claims_fixed_points_beyond_the_records_and_a_hardening_one_does_not():
    """Beside a linear start whose one fixed point lies within the records, a cube of the output
    that softens the spring puts fixed points at ±√((1 − a1 − a2)/|k|), beyond the records' range:
    claimed where they lie within as far again as the range is wide, not further. A hardening cube
    adds none."""
    rng = np.random.default_rng(3)
    x = rng.standard_normal(1000)
    y = np.clip(np.cumsum(rng.standard_normal(1000)) * 0.01, -0.5, 0.5)
    y[0], y[1] = -0.5, 0.5  # the records' range: [−0.5, 0.5], one wide
    start = _model(["y[t-1]", "y[t-2]", "x[t-1]"], [A1, A2, GAIN])
    terms = ["y[t-1]", "y[t-2]", "x[t-1]", "y[t-1]^3"]
    stiffness = 1 - A1 - A2
    for at, claimed in ((0.8, True), (1.4, True), (1.6, False)):
        softening = _model(terms, [A1, A2, GAIN, stiffness / at**2])
        beyond = beyond_the_records(start, softening, [(x, y)])
        level = GAIN * float(np.mean(x))  # the input's mean shifts the roots a little
        expected = _real_roots([stiffness / at**2, 0.0, -stiffness, level], -1.5, 1.5)
        expected = expected[np.abs(expected) > 0.5]
        assert len(beyond) == (expected.size if claimed else 0) == (2 if claimed else 0)
        np.testing.assert_allclose(beyond, expected, atol=3.0 / (LEVELS - 1))
    hardening = _model(terms, [A1, A2, GAIN, -stiffness])
    assert beyond_the_records(start, hardening, [(x, y)]) == ()


def test_with_nothing_declared_a_model_at_rest_beyond_the_records_is_not_returned():
    """The rig with a quadratic spring on mass 2 (3·10⁵ N/m², 200 N of unmeasured force), seed
    8008: the spring and the rig's cubic make two wells, and this record of 1600 samples stays in
    the one at −0.3 m. With nothing declared the loop named the rig's cubic spring, a signed power
    law of the output and a polynomial: their model ran free over the held-out tail at 1.5 % of the
    linear start's RMS and was returned, and over 4000 samples from another seed, which leave the
    well for the one at 0, it ran free three times as far off as the start, settled in a well at
    +0.3 m that the cube and the odd power law mirror from −0.3. It comes to rest beyond the
    record's outputs where the start does not, and is refused: the start is returned, and the
    report says why."""
    scenario = Scenario(disturbance_std=200.0, effects=Effects.parse(["quadratic_stiffness2=3e5"]))
    record, other = simulate(scenario, 1600, 8008), simulate(scenario, 4000, 58008)
    report = refine_records([(record.x, record.y)], [(other.x, other.y)], None)
    result, held_out = report.refinement, report.refinement.held_out
    assert held_out is not None and not held_out.kept and not result.effects_added
    assert held_out.fixed_points_beyond
    assert all(not record.y.min() <= level <= record.y.max() for level in held_out.fixed_points_beyond)
    assert report.after.free_run_rms <= report.before.free_run_rms
    assert any("comes to rest at" in note for note in report.to_dict()["notes"])
