"""A baseline's terms chosen from healthy records (models/baseline_choice.py): the orders and the
input delay by the held-out simulation, nonlinear terms only where they lower it."""

from __future__ import annotations

import numpy as np
import pytest

from harness.accelerometer import record, scenario
from harness.api_helpers import simulated
from models.baseline_choice import CHOICE_MIN_SAMPLES, choose_baseline_terms
from models.errors import InputError


def test_the_rig_gets_its_order_and_its_cubic_stiffness() -> None:
    """The paper rig (SPEC §2) is fourth-order, its input a sample late, with a cubic spring: the
    choice finds the delay and an order of four or more, and adds cubic terms of the output, which
    simulate the held-out parts better than the linear model could."""
    records = [simulated("none", 0.0, [5, i], n=4000) for i in range(2)]
    choice = choose_baseline_terms([(r.x, r.y) for r in records])
    # Fourth-order: no smaller model simulates it best (margin 0 may take one more, by chance).
    assert choice.ny == choice.nx and 4 <= choice.ny <= 5 and choice.delay == 1
    assert choice.added and all(term.degree == 3 for term in choice.added)
    assert all(factor.signal == "y" for term in choice.added for factor in term.factors)
    assert choice.terms[: -len(choice.added)] == tuple(t for t in choice.terms if t.degree == 1)
    assert choice.held_out_nrmse < 0.1 and choice.held_out_samples > 2000


def test_a_linear_structure_gets_no_nonlinear_terms_and_its_acceleration_x_t() -> None:
    """The chain's accelerometer: linear, and the force felt at once (delay 0). What FROLS offers
    beyond the linear terms does not lower the held-out free run, and is not kept."""
    choice = choose_baseline_terms([record(scenario(), 2000, 100 + i) for i in range(3)])
    assert choice.delay == 0 and choice.added == ()
    assert "x[t]" in [term.name for term in choice.terms]
    assert choice.held_out_nrmse < 0.05
    assert choice.to_dict()["terms_added"] == [] and choice.to_dict()["delay"] == 0


def test_records_it_cannot_choose_from_are_refused() -> None:
    rng = np.random.default_rng(3)
    with pytest.raises(
        InputError, match=f"300 samples is too short; this needs at least {CHOICE_MIN_SAMPLES}"
    ):
        choose_baseline_terms([(rng.normal(size=300), rng.normal(size=300))])
    # Values so small that no fit is possible: every linear candidate fails, said as such (it
    # answered "min() arg is an empty sequence").
    tiny = [(rng.normal(size=700) * 1e-300, rng.normal(size=700) * 1e-300)]
    with pytest.raises(InputError, match="no linear model of order 1 to 6 could be fitted"):
        choose_baseline_terms(tiny)


def test_a_sensor_offset_gets_one_constant() -> None:
    """An accelerometer whose zero is off: the linear start takes the constant, and the nonlinear
    terms offered beside it do not offer it again (it answered "term 1 is listed twice")."""
    records = [record(scenario(), 2000, 100 + i) for i in range(3)]
    offset = [(x, y + 2 * np.std(y)) for x, y in records]
    choice = choose_baseline_terms(offset)
    names = [term.name for term in choice.terms]
    assert names.count("1") == 1
    assert "1" not in [term.name for term in choice.added]
    assert choice.held_out_nrmse < 0.05
