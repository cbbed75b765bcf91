"""Column-scaled least squares (models.regression) against numpy and statsmodels."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from conftest import scaled_lstsq
from scipy import linalg

from models.errors import InputError
from models.regression import (
    SPAN_TOLERANCE,
    column_norms,
    least_squares,
    orthogonal_part,
    span_basis,
    subtract_outer,
    triangular_factor,
)

# statsmodels, the independent reference of a few tests, is imported in them: every pytest-xdist
# process imports every test module at collection, and statsmodels brings pandas and patsy.

EPS = np.finfo(float).eps


def badly_scaled_problem(seed: int, n: int = 400) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Columns of magnitude 1 and 1e-10 (like y and the b1·x column of the NARX), noisy target."""
    rng = np.random.default_rng(seed)
    Phi = np.column_stack([rng.normal(size=n), rng.normal(size=n) * 1e-10, rng.normal(size=n) + 0.3])
    theta = np.array([0.7, 3e9, -1.2])
    target = Phi @ theta + 0.05 * rng.normal(size=n)
    return Phi, target, theta


def test_matches_numpy_lstsq_on_badly_scaled_problem() -> None:
    Phi, target, _ = badly_scaled_problem(1)
    fit = least_squares(Phi, target)
    # Reference 1: numpy's SVD solver on the unit-norm columns (condition ~1 here).
    np.testing.assert_allclose(fit.theta, scaled_lstsq(Phi, target), rtol=1e-12)
    # Reference 2: numpy's solver on the raw columns. Its error is ~eps·cond(raw)·|θ| per
    # coefficient relative to the largest singular direction; cond(raw) ≈ 1e10, so ~1e-6.
    raw, *_ = np.linalg.lstsq(Phi, target, rcond=None)
    cond_raw = np.linalg.cond(Phi)
    assert 1e9 < cond_raw < 1e11
    np.testing.assert_allclose(fit.theta, raw, rtol=100 * EPS * cond_raw)
    # Residuals are those of the returned θ.
    np.testing.assert_allclose(fit.residuals, target - Phi @ fit.theta, rtol=0, atol=1e-14)
    assert fit.sigma2 == pytest.approx(np.mean(fit.residuals**2), rel=1e-14)
    # The scaled design is well conditioned, which is the point of scaling.
    assert fit.condition < 10


def test_recovers_exact_solution_of_consistent_badly_scaled_system() -> None:
    Phi, _, theta = badly_scaled_problem(2)
    fit = least_squares(Phi, Phi @ theta)
    # Scaled design has condition < 10, so the relative error is a few eps.
    np.testing.assert_allclose(fit.theta, theta, rtol=1e-13)
    assert fit.sigma2 < (1e-14 * np.linalg.norm(Phi @ theta)) ** 2


def test_covariance_is_sigma2_times_inverse_gram() -> None:
    from statsmodels.regression.linear_model import OLS

    rng = np.random.default_rng(3)
    n = 500
    Phi = np.column_stack([np.ones(n), rng.normal(size=n), rng.uniform(-1, 1, size=n)])
    target = Phi @ np.array([1.0, -2.0, 0.5]) + 0.3 * rng.normal(size=n)
    fit = least_squares(Phi, target)
    residuals = target - Phi @ np.linalg.solve(Phi.T @ Phi, Phi.T @ target)
    sigma2 = np.mean(residuals**2)
    np.testing.assert_allclose(fit.covariance, sigma2 * np.linalg.inv(Phi.T @ Phi), rtol=1e-10)
    # statsmodels divides the residual sum of squares by N − p; the library by N (SPEC §3).
    ols = OLS(target, Phi).fit()
    np.testing.assert_allclose(fit.theta, ols.params, rtol=1e-12)
    np.testing.assert_allclose(fit.covariance, ols.cov_params() * (n - 3) / n, rtol=1e-10)
    assert fit.sigma2 == pytest.approx(ols.ssr / n, rel=1e-12)


def test_covariance_on_badly_scaled_problem_matches_statsmodels() -> None:
    from statsmodels.regression.linear_model import OLS

    Phi, target, _ = badly_scaled_problem(4)
    fit = least_squares(Phi, target)
    ols = OLS(target, Phi).fit()
    n, p = Phi.shape
    # statsmodels inverts the raw Gram matrix by pinv: accurate to ~eps·cond(raw) only.
    tolerance = 100 * EPS * np.linalg.cond(Phi)
    # Compare standard errors and correlations: each must be right in its own units.
    se = np.sqrt(np.diag(fit.covariance))
    np.testing.assert_allclose(se, ols.bse * np.sqrt((n - p) / n), rtol=tolerance)
    correlation = fit.covariance / np.outer(se, se)
    np.testing.assert_allclose(correlation, ols.cov_params() / np.outer(ols.bse, ols.bse), atol=tolerance)


def test_zero_column_raises_naming_it() -> None:
    rng = np.random.default_rng(5)
    Phi = np.column_stack([rng.normal(size=50), np.zeros(50), rng.normal(size=50)])
    with pytest.raises(InputError, match=r"regressor x\[t-4\] is identically zero"):
        least_squares(Phi, rng.normal(size=50), ["y[t-1]", "x[t-4]", "y[t-2]"])
    with pytest.raises(InputError, match="column 1 is identically zero"):
        least_squares(Phi, rng.normal(size=50))


def test_collinear_columns_raise_naming_a_column_of_the_dependent_set() -> None:
    rng = np.random.default_rng(6)
    a, b = rng.normal(size=80), rng.normal(size=80)
    Phi = np.column_stack([a, b, 2.5 * a - b])
    with pytest.raises(InputError, match="linearly dependent") as info:
        least_squares(Phi, rng.normal(size=80), ["first", "second", "third"])
    message = str(info.value)
    assert any(f"{name} is explained by the others" in message for name in ("first", "second", "third"))
    # An exact duplicate: the later copy is the one explained by the earlier one.
    Phi = np.column_stack([a, b, a])
    with pytest.raises(InputError, match="dup is explained by the others"):
        least_squares(Phi, rng.normal(size=80), ["orig", "other", "dup"])


def test_nearly_collinear_beyond_double_precision_raises() -> None:
    rng = np.random.default_rng(7)
    a, b = rng.normal(size=80), rng.normal(size=80)
    Phi = np.column_stack([a, b, a + 1e-14 * b])
    with pytest.raises(InputError, match="condition number"):
        least_squares(Phi, rng.normal(size=80))


@pytest.mark.parametrize("rows", [2, 3])
def test_too_few_rows_raise(rows: int) -> None:
    rng = np.random.default_rng(8)
    with pytest.raises(InputError, match=f"{rows} usable samples cannot determine 3 parameters"):
        least_squares(rng.normal(size=(rows, 3)), rng.normal(size=rows))


def test_overflowing_regressor_is_named() -> None:
    Phi = np.column_stack([np.linspace(1, 2, 50), np.full(50, np.inf)])
    with pytest.raises(InputError, match="regressor b overflows"):
        least_squares(Phi, np.ones(50), ["a", "b"])


def test_a_candidate_nearly_in_the_models_span_is_projected_off_it_to_working_precision():
    """Gram–Schmidt once leaves a column that lies nearly in the model's span with a remainder
    that is not orthogonal to it (its error ~ eps·‖column‖, large against a remainder of 1e-9);
    the columns that lost most of their norm are projected again. Both kinds in one call: the
    remainders must be orthogonal to the model and equal to those of an SVD least-squares fit."""
    rng = np.random.default_rng(7)
    Q, _ = linalg.qr(rng.normal(size=(5000, 20)), mode="economic")
    nearly = Q @ rng.normal(size=20) + 1e-9 * rng.normal(size=5000)
    apart = rng.normal(size=5000)
    columns = np.column_stack([nearly, apart])
    remainders = orthogonal_part(columns / np.linalg.norm(columns, axis=0), Q)
    once = nearly - Q @ (Q.T @ nearly)
    assert np.max(np.abs(Q.T @ once)) / np.linalg.norm(once) > 1e-9  # once is not enough here
    for remainder in remainders.T:
        assert np.max(np.abs(Q.T @ remainder)) < 1e-13 * np.linalg.norm(remainder)
    for column, remainder in zip((columns / np.linalg.norm(columns, axis=0)).T, remainders.T, strict=True):
        fitted = Q @ linalg.lstsq(Q, column, lapack_driver="gelsd")[0]
        assert np.allclose(remainder, column - fitted, rtol=0, atol=1e-12)


def test_the_span_basis_projects_as_an_svd_basis_does_and_leaves_out_repeated_columns():
    """The noise family is tested against a basis of the span of every other family's chosen
    columns (models.scoring): the basis must be orthonormal to rounding, project any vector as
    scipy's SVD basis of the same span does, and leave out a column that repeats others (two
    families choosing one regressor), keeping one that is only nearly collinear (κ ≈ 10⁵)."""
    rng = np.random.default_rng(11)
    base = rng.normal(size=(20_000, 30)) * np.logspace(0, 3, 30)  # columns over three decades
    nearly = base[:, 0] + 1e-5 * np.linalg.norm(base[:, 0]) * rng.normal(size=20_000) / np.sqrt(20_000)
    columns = np.column_stack([base, 2.5 * base[:, 3] - base[:, 7], nearly])
    basis = span_basis(columns)
    reference = linalg.orth(columns / np.linalg.norm(columns, axis=0), rcond=SPAN_TOLERANCE)
    assert basis.shape == reference.shape == (20_000, 31)  # the repeat left out, the near one kept
    assert np.max(np.abs(basis.T @ basis - np.eye(31))) < 1e-13
    vectors = rng.normal(size=(20_000, 5))
    projected = basis @ (basis.T @ vectors)
    assert np.allclose(projected, reference @ (reference.T @ vectors), rtol=0, atol=1e-10)
    assert span_basis(np.empty((50, 0))).shape == (50, 0)


@pytest.mark.parametrize("rows", [5000, 4096, 2049])
def test_the_blockwise_triangular_factor_is_that_of_one_qr(rows: int) -> None:
    """TSQR's R agrees with LAPACK's on the whole matrix up to its rows' signs, whatever the last
    block holds (a full block, or one row, fewer than the columns); its blocks factored by two
    threads, it is the same to the last bit."""
    rng = np.random.default_rng(rows)
    A = rng.normal(size=(rows, 30)) * np.logspace(0, 6, 30)  # columns over six decades
    R = triangular_factor(A, block=2048)
    reference = linalg.qr(A, mode="r")[0][:30]
    signs = np.sign(np.diag(R) * np.diag(reference))
    assert R.shape == (30, 30)
    error = np.abs(signs[:, None] * R - reference)
    assert np.all(error <= 1e-13 * np.linalg.norm(A, axis=0))  # each column to its own scale
    with ThreadPoolExecutor(2) as pool:
        np.testing.assert_array_equal(triangular_factor(A, block=2048, threads=pool.map), R)


@pytest.mark.parametrize("rows", [7, 2049, 65_062])
def test_column_norms_are_numpys_to_the_last_bit_in_every_layout(rows: int) -> None:
    """The loop's scores and fits divide by these norms, and its reports are compared across
    changes byte for byte: einsum's sums must be numpy's own, row-major or not, for one column
    (which numpy sums pairwise) or many, over entries spanning many decades, a slice included."""
    rng = np.random.default_rng(rows)
    for width in (1, 2, 3, 4, 10, 51):
        columns = rng.normal(size=(rows, width)) * np.logspace(-8, 8, width)
        for layout in (columns, np.asfortranarray(columns), columns[1:, ::-1], columns[::2]):
            np.testing.assert_array_equal(column_norms(layout), np.linalg.norm(layout, axis=0))
    assert column_norms(np.empty((rows, 0))).shape == (0,)


@pytest.mark.parametrize("rows", [1, 7, 2049])
def test_an_outer_product_subtracted_in_place_is_numpys_to_the_last_bit(rows: int) -> None:
    """The greedy selection deflates a family's columns by W −= w·vᵀ at each step, and the loop's
    reports are compared across changes byte for byte: every entry as numpy's product and
    difference make it, over entries spanning many decades, row-major or not, where an entry
    computed as one fused multiply–add would differ in its last bit."""
    rng = np.random.default_rng(rows)
    for width in (1, 3, 30):
        W = rng.normal(size=(rows, width)) * np.logspace(-6, 6, width)
        w, v = rng.normal(size=rows), rng.normal(size=width) * 1e3
        for layout in (W, np.asfortranarray(W)):
            expected = layout.copy()
            expected -= np.outer(w, v)
            ours = layout.copy(order="A")
            subtract_outer(ours, w, v)
            np.testing.assert_array_equal(ours, expected)
    # The premise: a fused multiply–add, rounded once, differs from numpy's entries somewhere.
    W, w, v = rng.normal(size=(2049, 30)), rng.normal(size=2049), rng.normal(size=30)
    expected = W - np.outer(w, v)
    exact = (W.astype(np.longdouble) - w[:, None].astype(np.longdouble) * v).astype(float)
    assert np.any(exact != expected)
