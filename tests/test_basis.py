"""Functional bases on the normalised fault magnitude (SPEC §4) against scipy."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import special

from models.basis import FunctionalBasis
from models.errors import InputError

K_MIN, K_MAX = -32.0, 32.0
K_GRID = np.linspace(K_MIN, K_MAX, 41)


@pytest.mark.parametrize(("k_min", "k_max"), [(-32.0, 32.0), (0.0, 40.0), (-5.0, 17.5)])
def test_normalisation_maps_range_to_unit_interval(k_min: float, k_max: float) -> None:
    basis = FunctionalBasis("chebyshev2", 2, k_min, k_max)
    assert basis.normalise(k_min) == pytest.approx(-1.0, abs=1e-15)
    assert basis.normalise(k_max) == pytest.approx(1.0, abs=1e-15)
    assert basis.normalise((k_min + k_max) / 2) == pytest.approx(0.0, abs=1e-15)
    k = np.linspace(k_min, k_max, 7)
    np.testing.assert_allclose(basis.normalise(k), (2 * k - k_max - k_min) / (k_max - k_min), atol=1e-15)


@pytest.mark.parametrize("size", [1, 2, 3, 5, 8])
def test_chebyshev_second_kind_matches_scipy(size: int) -> None:
    basis = FunctionalBasis("chebyshev2", size, K_MIN, K_MAX)
    u = (2 * K_GRID - K_MAX - K_MIN) / (K_MAX - K_MIN)
    expected = np.column_stack([special.eval_chebyu(n, u) for n in range(size)])
    np.testing.assert_allclose(basis.values(K_GRID), expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("size", [1, 2, 3, 5, 8])
def test_legendre_matches_scipy(size: int) -> None:
    basis = FunctionalBasis("legendre", size, 0.0, 40.0)
    k = np.linspace(0.0, 40.0, 33)
    u = (2 * k - 40.0) / 40.0
    expected = np.column_stack([special.eval_legendre(n, u) for n in range(size)])
    np.testing.assert_allclose(basis.values(k), expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("size", [1, 2, 4])
def test_power_family_is_monomials_of_u(size: int) -> None:
    basis = FunctionalBasis("power", size, -10.0, 30.0)
    k = np.linspace(-10.0, 30.0, 9)
    u = (2 * k - 20.0) / 40.0
    np.testing.assert_allclose(basis.values(k), np.column_stack([u**n for n in range(size)]), atol=1e-15)


def test_values_shape_for_scalar_and_array() -> None:
    basis = FunctionalBasis("chebyshev2", 3, K_MIN, K_MAX)
    assert basis.values(5.0).shape == (3,)
    assert basis.values(K_GRID).shape == (41, 3)
    assert basis.derivatives(5.0).shape == (3,)
    np.testing.assert_allclose(basis.values(16.0), [1.0, 1.0, 0.0], atol=1e-15)  # u = 1/2


@pytest.mark.parametrize("family", ["chebyshev2", "legendre", "power"])
@pytest.mark.parametrize("size", [1, 2, 3, 6])
def test_derivatives_match_central_differences(family: str, size: int) -> None:
    """dg/dk in 1/percent. Central difference error: h²/6·|g'''| ≲ 1e-9 here plus rounding
    eps·|g|/h ≲ 1e-11; tolerance 1e-7 relative to the scale of the derivative."""
    basis = FunctionalBasis(family, size, K_MIN, K_MAX)
    k = np.linspace(K_MIN + 0.5, K_MAX - 0.5, 23)
    h = 1e-4
    numeric = (basis.values(k + h) - basis.values(k - h)) / (2 * h)
    analytic = basis.derivatives(k)
    scale = max(np.max(np.abs(numeric)), 2 / (K_MAX - K_MIN))
    np.testing.assert_allclose(analytic, numeric, atol=1e-7 * scale)


def test_chebyshev_derivative_closed_form() -> None:
    """U_n'(u) = ((n + 1)·T_{n+1}(u) − u·U_n(u))/(u² − 1), times du/dk = 2/(k_max − k_min)."""
    basis = FunctionalBasis("chebyshev2", 5, K_MIN, K_MAX)
    k = np.linspace(-30.0, 30.0, 13)
    u = k / 32.0
    expected = np.column_stack(
        [
            ((n + 1) * special.eval_chebyt(n + 1, u) - u * special.eval_chebyu(n, u)) / (u**2 - 1)
            for n in range(5)
        ]
    ) * (2 / 64.0)
    np.testing.assert_allclose(basis.derivatives(k), expected, rtol=1e-10, atol=1e-14)


def test_affine_only_for_at_most_two_functions() -> None:
    assert FunctionalBasis("chebyshev2", 2, 0, 1).is_affine
    assert FunctionalBasis("power", 1, 0, 1).is_affine
    assert not FunctionalBasis("legendre", 3, 0, 1).is_affine


def test_contains_is_the_closed_range() -> None:
    basis = FunctionalBasis("chebyshev2", 2, K_MIN, K_MAX)
    assert basis.contains(-32.0) and basis.contains(32.0) and basis.contains(0.0)
    assert not basis.contains(32.0001) and not basis.contains(-32.0001)


def test_document_round_trip() -> None:
    basis = FunctionalBasis("legendre", 4, -12.5, 30.0)
    assert FunctionalBasis.from_document(basis.to_document()) == basis
    np.testing.assert_array_equal(
        FunctionalBasis.from_document(basis.to_document()).values(K_GRID), basis.values(K_GRID)
    )


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (("hermite", 2, 0.0, 1.0), "unknown basis 'hermite'"),
        (("chebyshev2", 0, 0.0, 1.0), "at least one function"),
        (("chebyshev2", 2, 1.0, 1.0), "fault range [1.0, 1.0] is empty"),
        (("chebyshev2", 2, 5.0, -5.0), "is empty"),
    ],
)
def test_bad_bases_raise(args: tuple, fragment: str) -> None:
    with pytest.raises(InputError) as info:
        FunctionalBasis(*args)
    assert fragment in str(info.value)
