"""The exact NARX of the discretised structure (SPEC §2), checked three independent ways:
polynomial algebra written here, the SPEC's printed numbers, and a simulation loop written here."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import exact_narx_residual, reference_coefficients

from simulator.physics import PhysicalParameters
from simulator.theory import EXACT_TERMS, exact_coefficients, exact_fault_mode, exact_narx, exact_trajectories

EPS = np.finfo(float).eps


def test_exact_terms_are_the_eight_of_spec() -> None:
    assert [t.name for t in EXACT_TERMS] == [
        "y[t-1]",
        "y[t-2]",
        "y[t-3]",
        "y[t-4]",
        "y[t-2]^3",
        "y[t-3]^3",
        "y[t-4]^3",
        "x[t-4]",
    ]


def test_matches_spec_printed_healthy_coefficients(params) -> None:
    """SPEC §2 prints a ≈ [3.946369, −5.844459, 3.849759, −0.951669], cubic ≈ [−7.2713e-3,
    1.41790e-2, −6.9401e-3], b1 ≈ 3.2310e-11: each must agree to half a unit of its last digit."""
    c = exact_coefficients(params)
    for value, printed, unit in [
        (c[0], 3.946369, 1e-6),
        (c[1], -5.844459, 1e-6),
        (c[2], 3.849759, 1e-6),
        (c[3], -0.951669, 1e-6),
        (c[4], -7.2713e-3, 1e-7),
        (c[5], 1.41790e-2, 1e-7),
        (c[6], -6.9401e-3, 1e-7),
        (c[7], 3.2310e-11, 1e-15),
    ]:
        assert abs(value - printed) <= unit / 2, (value, printed)


def test_matches_spec_printed_k2_fault_coefficients(params) -> None:
    """SPEC §2: at k2 fault k = −32 / +32 %, b1 = 4.265e-11 / 2.197e-11 and a2 moves by
    ∓1.512e-3 (stiffening lowers a2, loosening raises it)."""
    healthy = exact_coefficients(params)
    stiff = exact_coefficients(params.with_fault("k2", -32.0))
    loose = exact_coefficients(params.with_fault("k2", 32.0))
    assert abs(stiff[7] - 4.265e-11) <= 0.5e-14
    assert abs(loose[7] - 2.197e-11) <= 0.5e-14
    assert abs((stiff[1] - healthy[1]) - (-1.512e-3)) <= 0.5e-6
    assert abs((loose[1] - healthy[1]) - 1.512e-3) <= 0.5e-6


@pytest.mark.parametrize(
    "changes",
    [
        {},
        {"k2": 90e3 * 1.32},
        {"k2": 90e3 * 0.68},
        {"k1": 10e3 * 0.7},
        {"m1": 1.0, "m2": 5.5, "k1": 1e3, "k2": 9e3, "c1": 7.5, "c2": 3.0},
        {"m1": 3.0, "m2": 20.0, "k1": 2e4, "k2": 5e4, "k3": 1e5, "c1": 200.0, "c2": 80.0, "ts": 1e-3},
    ],
)
def test_matches_independent_polynomial_algebra(params, changes: dict) -> None:
    p = params.replace(**changes)
    np.testing.assert_allclose(exact_coefficients(p), reference_coefficients(p), rtol=1e-12)


def test_static_gain_is_one_over_k1(params) -> None:
    """At rest x1 = x2 and k1·x1 = F, so the linear static gain b1/(1 − Σa) is 1/k1."""
    for p in (params, params.with_fault("k2", 29.0), params.with_fault("k1", 30.0)):
        c = exact_coefficients(p)
        # 1 − Σa ≈ 3e-7 is formed from O(1) terms: ~eps/3e-7 ≈ 1e-9 relative precision.
        assert c[7] / (1 - np.sum(c[:4])) == pytest.approx(1 / p.k1, rel=1e-7)
        # The cubic coefficients sum like the cubic spring's static share: k3/k2·b1·(1 − Σa)·…;
        # at rest A1(1) = k1 + k2, so Σc = −k3·(k1 + k2)/lead = −k3·b1·(k1 + k2)/k2.
        assert np.sum(c[4:7]) == pytest.approx(-p.k3 * c[7] * (p.k1 + p.k2) / p.k2, rel=1e-7)


@pytest.mark.parametrize("name", ["k1", "k2", "c1", "c2"])
def test_coefficients_affine_in_each_stiffness_and_damper(params, name: str) -> None:
    """SPEC §2: every coefficient is affine in any single stiffness k1, k2 and damper."""
    base = getattr(params, name)
    lo, mid, hi = (exact_coefficients(params.replace(**{name: base * f})) for f in (0.6, 1.0, 1.4))
    scale = np.abs(mid) + np.abs(hi - lo)
    assert np.all(np.abs((lo + hi) / 2 - mid) <= 1e-9 * scale)


def test_coefficients_are_not_affine_in_mass(params) -> None:
    """A control for the previous test: the masses enter the leading coefficient."""
    lo, mid, hi = (exact_coefficients(params.replace(m1=params.m1 * f)) for f in (0.6, 1.0, 1.4))
    assert np.max(np.abs((lo + hi) / 2 - mid) / np.abs(mid)) > 1e-3


def test_trajectories_and_fault_mode(params) -> None:
    ks = np.array([-32.0, -3.0, 0.0, 29.0])
    traj = exact_trajectories(params, "k2", ks)
    assert traj.shape == (4, 8)
    for row, k in zip(traj, ks, strict=True):
        np.testing.assert_allclose(row, reference_coefficients(params.with_fault("k2", k)), rtol=1e-12)
    np.testing.assert_array_equal(
        exact_trajectories(params, "k2", 5.0), exact_trajectories(params, "k2", [5.0])
    )
    mode = exact_fault_mode(params, "k1", -32.0, 32.0)
    assert mode.name == "k1" and mode.basis.size == 2 and mode.basis.family == "chebyshev2"
    for k in (-32.0, 7.0, 30.0):
        np.testing.assert_allclose(
            mode.coefficients(k), reference_coefficients(params.with_fault("k1", k)), rtol=1e-10
        )
    assert not np.any(mode.covariance)


def test_exact_narx_model(params) -> None:
    model = exact_narx(params)
    assert model.terms == EXACT_TERMS
    np.testing.assert_array_equal(model.theta, exact_coefficients(params))
    assert model.covariance.shape == (8, 8) and not np.any(model.covariance)


def independent_simulation(p: PhysicalParameters, force: np.ndarray) -> np.ndarray:
    """x2 from the forward-difference equations of SPEC §1, solved for the newest sample:
    m·(x[t+2] − 2x[t+1] + x[t])/Ts² + c·(x[t+1] − x[t])/Ts + restoring(t) = load(t)."""
    n = len(force)
    x1, x2 = np.zeros(n + 2), np.zeros(n + 2)
    for t in range(n):
        f1 = force[t] - (p.k1 + p.k2) * x1[t] + p.k2 * x2[t] - p.c1 * (x1[t + 1] - x1[t]) / p.ts
        f2 = p.k2 * x1[t] - p.k2 * x2[t] - p.k3 * x2[t] ** 3 - p.c2 * (x2[t + 1] - x2[t]) / p.ts
        x1[t + 2] = 2 * x1[t + 1] - x1[t] + p.ts**2 * f1 / p.m1
        x2[t + 2] = 2 * x2[t + 1] - x2[t] + p.ts**2 * f2 / p.m2
    return x2[:n]


@pytest.mark.parametrize(("mode", "k"), [("none", 0.0), ("k2", -32.0), ("k2", 29.0), ("k1", 30.0)])
def test_exact_narx_holds_on_an_independent_simulation(params, mode: str, k: float) -> None:
    """The eight-term NARX reproduces an independently written simulation to rounding error
    (SPEC §2: ~1e-15 relative); terms of size up to 6·|y| bound the rounding by ~1e3·eps·|y|."""
    p = params.with_fault(mode, k)
    force = np.random.default_rng(17).normal(0.0, 25e3, 3000)
    y = independent_simulation(p, force)[500:]
    x = force[500:]
    residual = exact_narx_residual(x, y, exact_coefficients(p))
    assert np.max(np.abs(residual)) < 1e3 * EPS * np.max(np.abs(y))
    # The check has teeth: the healthy coefficients on a 29 % k2 fault leave a visible residual.
    if mode != "none":
        wrong = exact_narx_residual(x, y, exact_coefficients(params))
        assert np.max(np.abs(wrong)) > 1e6 * np.max(np.abs(residual))
