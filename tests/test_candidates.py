"""Candidate dictionaries and the stacked candidate matrix (models.candidates)."""

from __future__ import annotations

from itertools import combinations_with_replacement
from math import comb

import numpy as np
import pytest
from conftest import hand_regressors

from models.candidates import candidate_matrix, candidate_terms
from models.errors import InputError
from models.terms import parse_terms, regressor_matrix
from simulator.simulate import Scenario, simulate


def structure(term) -> list[tuple[str, int, int]]:
    return [(f.signal, f.lag, f.power) for f in term.factors]


@pytest.mark.parametrize(("degree", "ny", "nx"), [(3, 4, 4), (2, 3, 1), (1, 2, 5), (4, 2, 2)])
def test_dictionary_holds_every_monomial_once(degree, ny, nx) -> None:
    """C(n + d, d) monomials of n variables up to degree d, the constant included."""
    terms = candidate_terms(degree, ny, nx)
    assert len(terms) == comb(ny + nx + degree, degree)
    assert len(set(terms)) == len(terms)
    assert len(candidate_terms(degree, ny, nx, constant=False)) == len(terms) - 1
    assert all(1 <= t.degree <= degree for t in terms[1:])


def test_paper_dictionary_has_165_candidates_in_sysidentpy_order() -> None:
    """Constant, then each degree in combinations_with_replacement order over
    (y[t-1] … y[t-4], x[t-1] … x[t-4]): SysIdentPy's regressor order for ylag = xlag = 4."""
    terms = candidate_terms()
    variables = [("y", lag) for lag in range(1, 5)] + [("x", lag) for lag in range(1, 5)]
    expected = [[]]
    for degree in (1, 2, 3):
        for combo in combinations_with_replacement(variables, degree):
            powers: dict[tuple[str, int], int] = {}
            for variable in combo:
                powers[variable] = powers.get(variable, 0) + 1
            expected.append([(s, lag, p) for (s, lag), p in powers.items()])
    assert len(terms) == 165
    assert [structure(t) for t in terms] == expected
    assert [t.name for t in terms[:10]] == [
        "1", "y[t-1]", "y[t-2]", "y[t-3]", "y[t-4]", "x[t-1]", "x[t-2]", "x[t-3]", "x[t-4]", "y[t-1]^2",
    ]  # fmt: skip
    assert terms[-1].name == "x[t-4]^3"


def test_names_parse_back_to_the_same_terms() -> None:
    terms = candidate_terms(3, 4, 4, delay=0, extra=["y[t-6]^5"])
    assert parse_terms([t.name for t in terms]) == terms


def test_delay_shifts_the_input_lags() -> None:
    x_lags = {f.lag for t in candidate_terms(1, 2, 3, delay=4) for f in t.factors if f.signal == "x"}
    assert x_lags == {4, 5, 6}
    assert "x[t]" in {t.name for t in candidate_terms(1, 1, 1, delay=0)}


def test_extra_terms_are_appended_and_duplicates_refused() -> None:
    terms = candidate_terms(2, 2, 2, extra=["y[t-1]^3", "y[t-5]*x[t-1]"])
    assert [t.name for t in terms[-2:]] == ["y[t-1]^3", "y[t-5]*x[t-1]"]
    with pytest.raises(InputError, match=r"extra term y\[t-1\]\^2 is already in the dictionary"):
        candidate_terms(2, 2, 2, extra=["y[t-1]^2"])
    with pytest.raises(InputError, match="listed twice"):
        candidate_terms(2, 2, 2, extra=["y[t-1]^3", "y[t-1]^3"])


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"degree": 0}, "degree must be an integer >= 1, got 0"),
        ({"ny": 0}, "ny must be an integer >= 1, got 0"),
        ({"nx": -1}, "nx must be an integer >= 1, got -1"),
        ({"delay": -1}, "delay must be an integer >= 0, got -1"),
        ({"degree": 2.5}, "degree must be an integer"),
        ({"extra": ["z[t-1]"]}, "cannot read term"),
    ],
)
def test_bad_dictionary_settings_are_refused(kwargs, message) -> None:
    with pytest.raises(InputError, match=message):
        candidate_terms(**kwargs)


@pytest.fixture(scope="module")
def records():
    return [simulate(Scenario(disturbance_std=800.0), n, seed=s) for n, s in ((400, 71), (300, 72))]


def test_matrix_equals_hand_built_regressors_column_by_column(records) -> None:
    """Every column (built from a parent column or from scratch) against an explicit loop over t."""
    terms = candidate_terms(3, 3, 2, delay=2, extra=["y[t-6]^2*x[t-1]", "x[t-2]^4"])
    rec = records[0]
    matrix = candidate_matrix(terms, [(rec.x, rec.y)])
    assert matrix.lag == 6 and matrix.rows == (400 - 6,)
    Phi, target = hand_regressors([structure(t) for t in terms], rec.x, rec.y, 6)
    np.testing.assert_allclose(matrix.P, Phi, rtol=1e-14, atol=0)
    np.testing.assert_array_equal(matrix.target, target)
    np.testing.assert_allclose(matrix.scale, np.linalg.norm(Phi, axis=0), rtol=1e-13)
    assert matrix.P.flags.f_contiguous


def test_extra_terms_of_any_kind_equal_their_regressors(records) -> None:
    """Extra terms beyond monomials (differences, sign, abs, sinusoids) come from
    models.terms.regressor_matrix, or from a parent column when they have one."""
    extra = ["sign(dy[t-1])", "y[t-1]*sign(dy[t-1])", "dy[t-2]*abs(dy[t-2])", "cos(2pi*0.03*t)"]
    terms = candidate_terms(2, 2, 2, extra=extra)
    rec = records[0]
    matrix = candidate_matrix(terms, [(rec.x, rec.y)])
    Phi, _ = regressor_matrix(terms, rec.x, rec.y, matrix.lag)
    assert matrix.lag == 3  # dy[t-2] reads y[t-3]
    np.testing.assert_allclose(matrix.P, Phi, rtol=1e-14, atol=0)


def test_records_are_stacked_without_crossing_their_boundary(records) -> None:
    terms = candidate_terms(2, 2, 2)
    matrix = candidate_matrix(terms, [(r.x, r.y) for r in records])
    blocks = [hand_regressors([structure(t) for t in terms], r.x, r.y, 2) for r in records]
    np.testing.assert_allclose(matrix.P, np.vstack([b[0] for b in blocks]), rtol=1e-14, atol=0)
    np.testing.assert_array_equal(matrix.target, np.concatenate([b[1] for b in blocks]))
    assert matrix.rows == (398, 298) and matrix.n_obs == 696
    joined = candidate_matrix(terms, [(np.r_[records[0].x, records[1].x], np.r_[records[0].y, records[1].y])])
    assert joined.n_obs == 698  # two equations straddle the seam: exactly what stacking avoids


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda x, y: (x, np.r_[y[:9], np.nan, y[10:]]), "record 1: y has 1 NaN"),
        (lambda x, y: (x[:4], y[:4]), "4 samples is too short; this needs at least 5"),
        (lambda x, y: (x[:60], y[:60]), "56 usable samples cannot rank 165 candidate terms"),
        (lambda x, y: (x * 1e60, y), r"candidate x\[t-1\]\^3, .* overflows"),
    ],
)
def test_unusable_records_are_refused(records, mutate, message) -> None:
    x, y = mutate(records[0].x, records[0].y)
    with pytest.raises(InputError, match=message):
        candidate_matrix(candidate_terms(), [(x, y)])
