"""Term names, parsing and the regressor matrix (models.terms)."""

from __future__ import annotations

import re

import numpy as np
import pytest
from conftest import hand_regressors
from hypothesis import given, settings
from hypothesis import strategies as st

from models.errors import InputError
from models.terms import Factor, Term, max_lag, parse_terms, regressor_matrix


@pytest.mark.parametrize(
    "name", ["y[t-1]", "y[t-2]^3", "x[t-4]", "y[t-1]*x[t-2]", "1", "x[t]", "y[t-1]^2*y[t-3]*x[t]^2"]
)
def test_name_round_trip(name: str) -> None:
    term = Term.parse(name)
    assert term.name == name
    assert Term.parse(term.name) == term


@pytest.mark.parametrize(
    ("name", "factors", "degree", "lag"),
    [
        ("y[t-1]", [("y", 1, 1)], 1, 1),
        ("y[t-2]^3", [("y", 2, 3)], 3, 2),
        ("x[t-4]", [("x", 4, 1)], 1, 4),
        ("y[t-1]*x[t-2]", [("y", 1, 1), ("x", 2, 1)], 2, 2),
        ("1", [], 0, 0),
        ("x[t]", [("x", 0, 1)], 1, 0),
    ],
)
def test_parse_reads_signal_lag_power(name: str, factors: list, degree: int, lag: int) -> None:
    term = Term.parse(name)
    assert [(f.signal, f.lag, f.power) for f in term.factors] == factors
    assert term.degree == degree
    assert term.max_lag == lag


def test_repeated_factors_merge_into_powers() -> None:
    assert Term.parse("y[t-1]*y[t-1]") == Term.parse("y[t-1]^2")
    assert Term.parse("y[t-1]*y[t-1]").name == "y[t-1]^2"
    assert Term.parse("y[t-2]^2*y[t-2]") == Term.parse("y[t-2]^3")
    # Order of the factors does not matter; the name is canonical (y before x, by lag).
    assert Term.parse("x[t-2]*y[t-1]") == Term.parse("y[t-1]*x[t-2]")
    assert Term.parse("x[t-2]*y[t-3]*y[t-1]").name == "y[t-1]*y[t-3]*x[t-2]"
    assert Term.parse(" y[t-1] * x[t-2] ") == Term.parse("y[t-1]*x[t-2]")


factor_strategy = st.builds(
    lambda signal, lag, power: Factor(signal, lag + (signal == "y"), power),
    st.sampled_from(["y", "x"]),
    st.integers(0, 12),
    st.integers(1, 4),
)


@settings(max_examples=200, deadline=None)
# Up to two factors of power ≤ 4: merged powers stay within MAX_POWER.
@given(st.lists(factor_strategy, max_size=2))
def test_any_product_round_trips_and_keeps_degree(factors: list[Factor]) -> None:
    term = Term.of(factors)
    assert Term.parse(term.name) == term
    assert term.degree == sum(f.power for f in factors)
    assert term.max_lag == max((f.lag for f in factors), default=0)
    # Shuffling the factors gives the same term.
    assert Term.of(reversed(factors)) == term


@pytest.mark.parametrize(
    ("name", "fragment"),
    [
        ("z[t-1]", "cannot read term 'z[t-1]'"),
        ("y[t+1]", "cannot read term"),
        ("y[t-1]^", "cannot read term"),
        ("y(t-1)", "cannot read term"),
        ("", "cannot read term"),
        ("2", "cannot read term"),
        ("y[t-1]**2", "cannot read term"),
        ("y[t]", "y needs a lag >= 1"),
        ("y[t-0]", "y needs a lag >= 1"),
        ("y[t-1]^0", "powers are >= 1"),
    ],
)
def test_bad_names_raise_input_error_with_guidance(name: str, fragment: str) -> None:
    with pytest.raises(InputError) as info:
        Term.parse(name)
    assert fragment in str(info.value)


def test_bad_name_message_shows_how_to_write_terms() -> None:
    with pytest.raises(InputError, match=r"y\[t-1\], y\[t-2\]\^3, x\[t-4\], dy\[t-1\], sign"):
        Term.parse("q[t-1]")


def test_parse_terms_refuses_empty_and_duplicates() -> None:
    with pytest.raises(InputError, match="at least one term"):
        parse_terms([])
    with pytest.raises(InputError, match=r"y\[t-1\]\^2 is listed twice"):
        parse_terms(["y[t-1]^2", "y[t-1]*y[t-1]"])
    assert parse_terms(["y[t-1]", Term.parse("x[t-4]")]) == (Term.parse("y[t-1]"), Term.parse("x[t-4]"))


def test_max_lag_of_a_structure() -> None:
    assert max_lag(parse_terms(["y[t-1]", "y[t-3]^3", "x[t-4]*y[t-2]"])) == 4
    assert max_lag(parse_terms(["1", "x[t]"])) == 0


def test_regressor_matrix_matches_hand_built_loop() -> None:
    rng = np.random.default_rng(5)
    x, y = rng.normal(size=60), rng.normal(size=60)
    names = ["1", "y[t-1]", "y[t-2]^3", "x[t]", "x[t-4]", "y[t-1]*x[t-2]", "y[t-1]^2*y[t-3]", "x[t-1]^2"]
    structure = [
        [],
        [("y", 1, 1)],
        [("y", 2, 3)],
        [("x", 0, 1)],
        [("x", 4, 1)],
        [("y", 1, 1), ("x", 2, 1)],
        [("y", 1, 2), ("y", 3, 1)],
        [("x", 1, 2)],
    ]
    terms = parse_terms(names)
    Phi, target = regressor_matrix(terms, x, y)
    Phi_ref, target_ref = hand_regressors(structure, x, y, lag=4)
    assert Phi.shape == (56, len(names))
    np.testing.assert_allclose(Phi, Phi_ref, rtol=1e-14, atol=0)
    np.testing.assert_array_equal(target, target_ref)


def test_regressor_matrix_with_a_longer_lag_drops_more_rows() -> None:
    rng = np.random.default_rng(6)
    x, y = rng.normal(size=30), rng.normal(size=30)
    terms = parse_terms(["y[t-1]", "x[t-2]"])
    Phi, target = regressor_matrix(terms, x, y, lag=6)
    Phi_ref, target_ref = hand_regressors([[("y", 1, 1)], [("x", 2, 1)]], x, y, lag=6)
    np.testing.assert_array_equal(Phi, Phi_ref)
    np.testing.assert_array_equal(target, target_ref)


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("x[t-1]^10", "at most 9"),
        ("y[t-10001]", "lags run from 0 to 10000"),
        ("y[t-1]^5*y[t-1]^5", "at most 9"),
    ],
)
def test_terms_beyond_physical_bounds_are_refused(name: str, message: str) -> None:
    with pytest.raises(InputError, match=message):
        Term.parse(name)


# --- beyond polynomials: differences, abs/sign, sinusoids --------------------------------------


@pytest.mark.parametrize(
    ("name", "reach"),
    [
        ("dy[t-1]", 2),
        ("sign(dy[t-1])", 2),
        ("dy[t-2]*abs(dy[t-2])", 3),
        ("dy[t-1]^3", 2),
        ("abs(dx[t])", 1),
        ("sin(2pi*0.0125*t)", 0),
        ("y[t-1]*cos(2pi*0.1*t)", 1),
        ("x[t-1]^2*sign(dx[t-3])", 4),
    ],
)
def test_derived_factors_round_trip_and_reach_one_sample_further(name: str, reach: int) -> None:
    term = Term.parse(name)
    assert term.name == name
    assert Term.parse(term.name) == term
    assert term.max_lag == reach


@pytest.mark.parametrize(
    ("name", "fragment"),
    [
        ("sign(dy[t-1])^2", "power of sign"),
        ("sign(dy[t-1])*sign(dy[t-1])", "power of sign"),
        ("spow(y[t-1],0.5)^2", "power of spow"),
        ("spow(y[t-1],0)", "exponent 0 < p <= 9"),
        ("apow(dy[t-1],12)", "exponent 0 < p <= 9"),
        ("deadzone(y[t-1],0.1)", "applies to the input x"),
        ("backlash(x[t-1],-1)", "half-width w > 0"),
        ("backlash(x[t-1],1e999)", "half-width w > 0"),
        ("spow(y[t-1],abc)", "cannot read term"),
        ("dy[t]", "lag 0 of dy"),
        ("sin(2pi*0.5*t)", "0 < f < 0.5"),
        ("cos(2pi*-0.1*t)", "0 < f < 0.5"),
        ("sin(2pi*abc*t)", "cannot read term"),
        ("sin(2pi*0.1*t", "cannot read term"),
    ],
)
def test_bad_derived_factors_are_refused(name: str, fragment: str) -> None:
    with pytest.raises(InputError, match=re.escape(fragment)):
        Term.parse(name)


def test_derived_regressors_match_a_hand_built_loop() -> None:
    rng = np.random.default_rng(3)
    x, y = rng.normal(size=60), rng.normal(size=60)
    names = [
        "sign(dy[t-1])",
        "dy[t-2]*abs(dy[t-2])",
        "dy[t-1]^3",
        "abs(dx[t])",
        "sin(2pi*0.05*t)",
        "cos(2pi*0.2*t)",
    ]
    t0, L = 7, 3
    Phi, target = regressor_matrix(parse_terms(names), x, y, lag=L, t0=t0)
    for row, t in enumerate(range(L, 60)):
        expected = [
            np.sign(y[t - 1] - y[t - 2]),
            (y[t - 2] - y[t - 3]) * abs(y[t - 2] - y[t - 3]),
            (y[t - 1] - y[t - 2]) ** 3,
            abs(x[t] - x[t - 1]),
            np.sin(2 * np.pi * 0.05 * (t0 + t)),
            np.cos(2 * np.pi * 0.2 * (t0 + t)),
        ]
        np.testing.assert_allclose(Phi[row], expected, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(target, y[L:])
