"""FNARX fault-mode models (SPEC §4) against the exact coefficient trajectories (SPEC §2)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import K2_MAGNITUDES, exact_regressors, scaled_lstsq
from scipy import stats

from models.basis import FunctionalBasis
from models.errors import InputError
from models.fnarx import FNARX, fit_fnarx
from models.narx import NARX
from simulator.simulate import Scenario, simulate
from simulator.theory import EXACT_TERMS, exact_coefficients, exact_fault_mode, exact_trajectories

K_CHECK = np.linspace(-32.0, 32.0, 65)


def test_design_and_bookkeeping(k2_model) -> None:
    assert k2_model.name == "k2"
    assert k2_model.terms == EXACT_TERMS
    assert k2_model.basis == FunctionalBasis("chebyshev2", 2, -32.0, 32.0)
    assert k2_model.theta.shape == (8, 2)
    assert k2_model.covariance.shape == (16, 16)
    np.testing.assert_array_equal(k2_model.experiment_k, K2_MAGNITUDES)
    assert k2_model.n_obs == 17 * (2000 - 4)


def test_kronecker_stacked_ols_matches_independent_computation(k2_model, k2_experiments) -> None:
    """y_k[t] = [φ_k[t] ⊗ g(k)]ᵀθ (SPEC §4), θ row-major (term i, then basis function j)."""
    rows, targets, per_run = [], [], []
    for x, y, k in k2_experiments.runs:
        Phi, target = exact_regressors(x, y)
        u = k / 32.0
        g = np.array([1.0, 2 * u])  # U_0, U_1
        rows.append(np.einsum("ti,j->tij", Phi, g).reshape(len(target), -1))
        targets.append(target)
        per_run.append(len(target))
    X, Y = np.vstack(rows), np.concatenate(targets)
    theta = scaled_lstsq(X, Y)
    residuals = Y - X @ theta
    sigma2 = [np.mean(e**2) for e in np.split(residuals, np.cumsum(per_run)[:-1])]
    np.testing.assert_allclose(k2_model.experiment_sigma2, sigma2, rtol=1e-6)
    # Covariance σ̂²(XᵀX)⁻¹ via the SVD of the column-scaled design (forming XᵀX would square
    # its condition number and lose the digits compared here).
    scale = np.linalg.norm(X, axis=0)
    _, s, Vt = np.linalg.svd(X / scale, full_matrices=False)
    covariance = np.mean(residuals**2) * (Vt.T / s**2) @ Vt / np.outer(scale, scale)
    np.testing.assert_allclose(k2_model.covariance, covariance, rtol=1e-6)
    # Two backward-stable solvers differ by ~cond(X/scale)·eps ≈ 1e-10 of the scaled solution,
    # far below one standard error; some slopes are ≈ 0 in theory, so compare in that unit.
    se = np.sqrt(np.diag(covariance))
    assert np.all(np.abs(k2_model.theta.ravel() - theta) < 1e-6 * se)


def test_trajectories_agree_with_theory_jointly(k2_model, params) -> None:
    """The estimated θ is Gaussian around the exact projection coefficients with covariance
    k2_model.covariance (white residuals, SPEC §1), so (θ̂ − θ)ᵀ Cov⁻¹ (θ̂ − θ) ~ χ²(16).
    Testing at the 0.999 quantile checks every trajectory at every k at once."""
    exact = exact_fault_mode(params, "k2", -32.0, 32.0)
    d = (k2_model.theta - exact.theta).ravel()
    chi2 = float(d @ np.linalg.solve(k2_model.covariance, d))
    assert chi2 < stats.chi2.ppf(0.999, df=16), chi2


def test_trajectories_within_simultaneous_bands(k2_model, params) -> None:
    """Pointwise 99 % intervals at 65 magnitudes, checked with a simultaneous guarantee.

    For coefficient i, θ̂_i(k) − θ_i(k) = g(k)ᵀd_i with d_i ~ N(0, C_i) (its 2×2 block of the
    covariance). By Cauchy–Schwarz, max over k of z_i(k)² = (g·d_i)²/(gᵀC_i g) is at most
    d_iᵀC_i⁻¹d_i ~ χ²(2), so P(max_k |z_i(k)| > r) ≤ exp(−r²/2). With r² the χ²(2) quantile at
    1 − 0.001/8 (Bonferroni over the eight coefficients), the whole check fails with probability
    ≤ 0.001 for a correct library, while a trajectory biased by a few standard errors fails it.
    The plain 99 % band (r = 2.576) is exceeded somewhere on [−32, 32] by a given coefficient
    with probability up to exp(−2.576²/2) ≈ 3.6 %, so it cannot be demanded at every point."""
    traj = k2_model.trajectories(K_CHECK, level=0.99)
    theory = exact_trajectories(params, "k2", K_CHECK)
    assert traj.term_names == [t.name for t in EXACT_TERMS]
    assert traj.values.shape == theory.shape == (65, 8)
    np.testing.assert_allclose(traj.values - traj.low, traj.high - traj.values, rtol=1e-12)
    se = (traj.high - traj.values) / stats.norm.ppf(0.995)
    expected_se = np.array([np.sqrt(np.diag(k2_model.coefficient_covariance(k))) for k in K_CHECK])
    # (high − value) loses ~eps·|θ|/se ≈ 1e-11 relative to cancellation.
    np.testing.assert_allclose(se, expected_se, rtol=1e-9)
    z = (traj.values - theory) / se
    radius = np.sqrt(stats.chi2.ppf(1 - 0.001 / 8, df=2))
    assert np.all(np.abs(z) < radius), np.abs(z).max(axis=0)
    # The per-coefficient 2-df statistics bound max_k z² as stated.
    exact = exact_fault_mode(params, "k2", -32.0, 32.0)
    for i in range(8):
        d = k2_model.theta[i] - exact.theta[i]
        C = k2_model.covariance[2 * i : 2 * i + 2, 2 * i : 2 * i + 2]
        assert np.max(z[:, i] ** 2) <= d @ np.linalg.solve(C, d) * (1 + 1e-9)


def test_standard_errors_of_trajectories_match_delta_method(k2_model) -> None:
    for k in (-32.0, -7.0, 0.0, 19.0, 32.0):
        g = np.array([1.0, 2 * k / 32.0])
        J = np.kron(np.eye(8), g)  # θ(k) = J·vec(θ)
        np.testing.assert_allclose(k2_model.coefficients(k), J @ k2_model.theta.ravel(), rtol=1e-13)
        np.testing.assert_allclose(
            k2_model.coefficient_covariance(k), J @ k2_model.covariance @ J.T, rtol=1e-10, atol=1e-40
        )


def test_noise_free_experiments_recover_exact_fault_mode(k2_noise_free_experiments, params) -> None:
    """Without noise only rounding remains: same floating-point argument as the NARX fit
    (cond(scaled design) ~1e6 × eps, amplified for the small cubic columns) gives ≲ 1e-9
    relative per coefficient; 1e-8 is required at every k."""
    model = fit_fnarx(k2_noise_free_experiments.runs, EXACT_TERMS, name="k2")
    exact = exact_fault_mode(params, "k2", -32.0, 32.0)
    estimated = np.array([model.coefficients(k) for k in K_CHECK])
    theory = exact_trajectories(params, "k2", K_CHECK)
    np.testing.assert_allclose(estimated, theory, rtol=1e-8)
    np.testing.assert_allclose(np.array([exact.coefficients(k) for k in K_CHECK]), theory, rtol=1e-12)
    assert np.all(model.experiment_sigma2 < (1e-13 * 0.1) ** 2)


def test_exact_fault_mode_is_exactly_affine(params) -> None:
    """SPEC §2: every coefficient is affine in k2, so p = 2 is exact at every k, not only at
    the two ends used to build the exact fault-mode model."""
    exact = exact_fault_mode(params, "k2", -32.0, 32.0)
    for k in (-32.0, -17.3, 0.0, 3.0, 29.0, 32.0):
        np.testing.assert_allclose(
            exact.coefficients(k), exact_coefficients(params.with_fault("k2", k)), rtol=1e-12
        )
    assert isinstance(exact.narx_at(3.0), NARX)
    np.testing.assert_array_equal(exact.narx_at(3.0).theta, exact.coefficients(3.0))


@pytest.mark.parametrize("family", ["legendre", "power"])
def test_other_bases_with_same_span_give_same_fit(k2_experiments, k2_model, family: str) -> None:
    other = fit_fnarx(k2_experiments.runs, EXACT_TERMS, name="k2", family=family, size=2)
    a = k2_model.trajectories(K_CHECK, level=0.95)
    b = other.trajectories(K_CHECK, level=0.95)
    np.testing.assert_allclose(b.values, a.values, rtol=1e-9)
    np.testing.assert_allclose(b.high - b.values, a.high - a.values, rtol=1e-6)
    np.testing.assert_allclose(other.experiment_sigma2, k2_model.experiment_sigma2, rtol=1e-6)
    # The projection coefficients themselves differ (different basis), unless the family is
    # identical: Legendre/power G_2 = u is half of Chebyshev U_1 = 2u.
    np.testing.assert_allclose(other.theta[:, 1], 2 * k2_model.theta[:, 1], rtol=1e-8)


def test_p3_basis_fits_and_quadratic_part_is_null(k2_experiments, params) -> None:
    """With p = 3 the extra U_2 coefficient estimates a curvature that theory says is zero."""
    model = fit_fnarx(k2_experiments.runs, EXACT_TERMS, name="k2", size=3)
    assert model.theta.shape == (8, 3)
    exact = exact_fault_mode(params, "k2", -32.0, 32.0)
    # Express the exact affine trajectories in U_0, U_1, U_2 (U_2 coefficient 0).
    truth = np.column_stack([exact.theta, np.zeros(8)]).ravel()
    d = model.theta.ravel() - truth
    assert float(d @ np.linalg.solve(model.covariance, d)) < stats.chi2.ppf(0.999, df=24)


def test_coefficients_outside_range_raise(k2_model) -> None:
    for k in (-32.5, 33.0, np.nan, np.inf):
        with pytest.raises(InputError, match=r"outside the range \[-32.0, 32.0\] of fault-mode model 'k2'"):
            k2_model.coefficients(k)
    with pytest.raises(InputError, match="outside the range"):
        k2_model.trajectories([0.0, 40.0])
    with pytest.raises(InputError, match="outside the range"):
        k2_model.narx_at(-50.0)


def test_document_round_trip(k2_model) -> None:
    document = k2_model.to_document()
    for restored in (FNARX.from_document(document), FNARX.from_document(json.loads(json.dumps(document)))):
        assert restored.name == k2_model.name
        assert restored.terms == k2_model.terms
        assert restored.basis == k2_model.basis
        np.testing.assert_array_equal(restored.theta, k2_model.theta)
        np.testing.assert_array_equal(restored.covariance, k2_model.covariance)
        np.testing.assert_array_equal(restored.experiment_k, k2_model.experiment_k)
        np.testing.assert_array_equal(restored.experiment_sigma2, k2_model.experiment_sigma2)
        assert restored.n_obs == k2_model.n_obs
    with pytest.raises(InputError, match="not a fnarx model document"):
        FNARX.from_document({**document, "kind": "narx"})
    with pytest.raises(InputError, match="do not match the terms"):
        FNARX.from_document({**document, "theta": k2_model.theta[:, :1].tolist()})


def test_sigma2_interpolates_between_experiments(k2_model) -> None:
    k, s2 = k2_model.experiment_k, k2_model.experiment_sigma2
    assert k2_model.sigma2_at(-32.0) == pytest.approx(s2[0], rel=1e-14)
    assert k2_model.sigma2_at(-30.0) == pytest.approx((s2[0] + s2[1]) / 2, rel=1e-12)
    assert k2_model.sigma2_at(float(k[8])) == pytest.approx(s2[8], rel=1e-14)


def test_fewer_distinct_magnitudes_than_basis_size_raise(k2_experiments) -> None:
    runs = k2_experiments.runs
    same_k = [(x, y, 4.0) for x, y, _ in runs[:3]]
    with pytest.raises(InputError, match="needs experiments at 2 or more distinct magnitudes, got 1"):
        fit_fnarx(same_k, EXACT_TERMS, name="k2")
    with pytest.raises(InputError, match="3 or more distinct magnitudes, got 2"):
        fit_fnarx(runs[:2], EXACT_TERMS, name="k2", size=3)


def test_bad_experiments_raise(k2_experiments) -> None:
    runs = k2_experiments.runs
    with pytest.raises(InputError, match="needs experiments"):
        fit_fnarx([], EXACT_TERMS, name="k2")
    with pytest.raises(InputError, match="finite fault magnitude"):
        fit_fnarx([*runs[:2], (runs[2][0], runs[2][1], np.nan)], EXACT_TERMS, name="k2")
    with pytest.raises(InputError, match="lies outside"):
        fit_fnarx(runs, EXACT_TERMS, name="k2", k_range=(-20.0, 20.0))
    x, y, k = runs[1]
    with pytest.raises(InputError, match=r"experiment 2 \(k=-28.0\): y has 1 NaN"):
        fit_fnarx([runs[0], (x, np.r_[y[:-1], np.nan], k), runs[2]], EXACT_TERMS, name="k2")


def test_explicit_k_range_is_used(k2_experiments) -> None:
    model = fit_fnarx(k2_experiments.runs[4:13], EXACT_TERMS, name="k2", k_range=(-32.0, 32.0))
    assert (model.basis.k_min, model.basis.k_max) == (-32.0, 32.0)
    default = fit_fnarx(k2_experiments.runs[4:13], EXACT_TERMS, name="k2")
    assert (default.basis.k_min, default.basis.k_max) == (-16.0, 16.0)
    # Same data, same span: same trajectories inside the common range.
    grid = np.linspace(-16.0, 16.0, 9)
    np.testing.assert_allclose(model.trajectories(grid).values, default.trajectories(grid).values, rtol=1e-9)


def test_fit_uses_each_experiments_own_lags(params) -> None:
    """Experiments are stacked without lags crossing between them: two noise-free
    experiments at different k determine the exact p = 2 model."""
    runs = [
        (r.x, r.y, k)
        for k, r in (
            (k, simulate(Scenario(fault="k2", k=k), 800, seed=s)) for k, s in ((-32.0, 51), (32.0, 52))
        )
    ]
    model = fit_fnarx(runs, EXACT_TERMS, name="k2")
    np.testing.assert_allclose(
        model.coefficients(10.0), exact_coefficients(params.with_fault("k2", 10.0)), rtol=1e-7
    )


def test_an_experiment_whose_cubic_sums_overflow_is_refused_by_name(k2_experiments) -> None:
    """One experiment scaled by 1e60 is named, with the overflow as its reason."""
    runs = list(k2_experiments.runs)
    x, y, k = runs[3]
    runs[3] = (x, y * 1e60, k)
    with pytest.raises(
        InputError, match=r"experiment 4 \(k=-20.0\): y reaches .* degree 3 the statistics overflow"
    ):
        fit_fnarx(runs, EXACT_TERMS, name="k2")
