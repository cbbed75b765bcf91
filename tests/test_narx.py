"""NARX identification on simulated records against the exact theory (SPEC §2, §3)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import DISTURBANCE_STD, exact_regressors, scaled_lstsq
from scipy import stats

from models.errors import InputError
from models.narx import NARX, fit_narx, z_quantile
from models.terms import parse_terms
from simulator.simulate import Scenario, simulate
from simulator.theory import EXACT_TERMS, exact_coefficients, exact_narx

EPS = np.finfo(float).eps
QUADRATIC = ["y[t-1]^2", "y[t-1]*y[t-2]", "y[t-2]*x[t-4]"]


def test_noise_free_fit_recovers_exact_coefficients(noise_free_record, params) -> None:
    """With no noise the only error is rounding, so the bound is a floating-point one.

    Backward-stable least squares on the column-scaled design Φs (θs = θ·‖Φ_j‖) gives a forward
    error ‖δθs‖ ≲ cond(Φs)·eps·‖y‖ when the residual is ~0. Per coefficient that is
    |δθ_j|/|θ_j| ≲ cond·eps·‖y‖/(‖Φ_j‖·|θ_j|): ~1e-11 for the linear AR terms, ~1e-9 for the
    cubic terms, whose columns carry only a small part of y. The test allows 100× that bound.
    """
    rec = noise_free_record
    model = fit_narx([(rec.x, rec.y)], EXACT_TERMS)
    theory = exact_coefficients(params)
    Phi, target = exact_regressors(rec.x, rec.y)
    norms = np.linalg.norm(Phi, axis=0)
    cond = np.linalg.cond(Phi / norms)
    assert cond < 1e7
    bound = cond * EPS * np.linalg.norm(target) / (norms * np.abs(theory))
    relative = np.abs(model.theta / theory - 1)
    assert np.all(relative < 100 * bound), (relative, bound)
    # And in absolute terms the estimates hold at least eight significant digits.
    assert np.all(relative < 1e-8)
    assert model.sigma2 < (1e-13 * np.std(rec.y)) ** 2
    assert model.n_obs == len(rec.y) - 4


def test_disturbed_fit_agrees_with_theory_within_standard_errors(disturbed_record, params) -> None:
    """A white force disturbance makes the NARX residual white (SPEC §1), so OLS is consistent
    and its covariance is right: every z-score |θ̂ − θ|/se is N(0, 1) and the joint statistic
    (θ̂ − θ)ᵀ Cov⁻¹ (θ̂ − θ) is χ²(8). Per-coefficient |z| < 4 fails with probability < 5e-4 for
    eight coefficients; the joint test is run at the 0.999 quantile."""
    rec = disturbed_record
    model = fit_narx([(rec.x, rec.y)], EXACT_TERMS)
    theory = exact_coefficients(params)
    z = (model.theta - theory) / model.standard_errors()
    assert np.all(np.abs(z) < 4), z
    d = model.theta - theory
    chi2 = float(d @ np.linalg.solve(model.covariance, d))
    assert chi2 < stats.chi2.ppf(0.999, df=8), chi2
    intervals = model.intervals(0.999)
    assert np.all((intervals[:, 0] <= theory) & (theory <= intervals[:, 1]))
    # The residual variance is that of b1·w: (b1·σ_w)², to within its sampling error
    # (relative standard error √(2/N) ≈ 0.8 %; 4σ allowed).
    expected = (theory[-1] * DISTURBANCE_STD) ** 2
    assert model.sigma2 == pytest.approx(expected, rel=4 * np.sqrt(2 / model.n_obs))


def test_intervals_use_normal_quantile(disturbed_record) -> None:
    model = fit_narx([(disturbed_record.x, disturbed_record.y)], EXACT_TERMS)
    se = model.standard_errors()
    np.testing.assert_allclose(se, np.sqrt(np.diag(model.covariance)))
    for level in (0.9, 0.95, 0.999):
        z = stats.norm.ppf(0.5 + level / 2)
        assert z_quantile(level) == pytest.approx(z, rel=1e-12)
        np.testing.assert_allclose(
            model.intervals(level), np.column_stack([model.theta - z * se, model.theta + z * se])
        )


def test_covariance_matches_independent_ols(disturbed_record) -> None:
    rec = disturbed_record
    model = fit_narx([(rec.x, rec.y)], EXACT_TERMS)
    Phi, target = exact_regressors(rec.x, rec.y)
    theta = scaled_lstsq(Phi, target)
    assert np.all(np.abs(model.theta - theta) < 1e-6 * model.standard_errors())
    sigma2 = np.mean((target - Phi @ theta) ** 2)
    scale = np.linalg.norm(Phi, axis=0)
    # (ΦsᵀΦs)⁻¹ = V·S⁻²·Vᵀ from the SVD of the scaled design: forming ΦsᵀΦs would square its
    # condition (~1e11) and lose five digits; the SVD keeps ~eps·cond(Φs) ≈ 1e-10.
    _, s, Vt = np.linalg.svd(Phi / scale, full_matrices=False)
    covariance = sigma2 * (Vt.T / s**2) @ Vt / np.outer(scale, scale)
    np.testing.assert_allclose(model.covariance, covariance, rtol=1e-7)


def test_quadratic_terms_are_estimated_as_zero(disturbed_record, params) -> None:
    """SPEC §2: the equations have no quadratic terms; a model carrying them must find ≈ 0."""
    rec = disturbed_record
    model = fit_narx([(rec.x, rec.y)], [*EXACT_TERMS, *QUADRATIC])
    truth = np.concatenate([exact_coefficients(params), np.zeros(len(QUADRATIC))])
    z = (model.theta - truth) / model.standard_errors()
    assert np.all(np.abs(z) < 4), dict(zip(model.term_names, z, strict=True))
    d = model.theta - truth
    assert float(d @ np.linalg.solve(model.covariance, d)) < stats.chi2.ppf(0.999, df=len(truth))


def test_quadratic_terms_are_exactly_zero_without_noise(noise_free_record) -> None:
    rec = noise_free_record
    model = fit_narx([(rec.x, rec.y)], [*EXACT_TERMS, *QUADRATIC])
    Phi, _ = exact_regressors(rec.x, rec.y)
    # A quadratic coefficient's contribution to y must be at rounding level, not a fitted effect.
    y1, y2, x4 = Phi[:, 0], Phi[:, 1], Phi[:, 7]
    contributions = [np.std(y1**2), np.std(y1 * y2), np.std(y2 * x4)]
    for coefficient, spread in zip(model.theta[-3:], contributions, strict=True):
        assert abs(coefficient) * spread < 1e-9 * np.std(rec.y)


def test_several_records_equal_stacking_each_record(params) -> None:
    """Each record contributes its own equations; lags never cross a record boundary."""
    recs = [
        simulate(Scenario(disturbance_std=DISTURBANCE_STD), n, seed=s) for n, s in ((900, 21), (1300, 22))
    ]
    model = fit_narx([(r.x, r.y) for r in recs], EXACT_TERMS)
    blocks = [exact_regressors(r.x, r.y) for r in recs]
    Phi = np.vstack([b[0] for b in blocks])
    target = np.concatenate([b[1] for b in blocks])
    # Two backward-stable solvers differ by ~cond(scaled Φ)·eps ≈ 1e-10 of the scaled solution:
    # compare in standard errors (the statistical precision), not relative to tiny θ's.
    difference = model.theta - scaled_lstsq(Phi, target)
    assert np.all(np.abs(difference) < 1e-6 * model.standard_errors())
    assert model.n_obs == 900 + 1300 - 8
    # The stacked fit differs from a fit that lets lags cross the seam by far more than that.
    joined = fit_narx(
        [(np.concatenate([r.x for r in recs]), np.concatenate([r.y for r in recs]))], EXACT_TERMS
    )
    assert np.max(np.abs(joined.theta - model.theta) / model.standard_errors()) > 1e-3


def test_several_noise_free_records_give_exact_model_but_concatenation_would_not(params) -> None:
    recs = [simulate(Scenario(), 1500, seed=s) for s in (31, 32)]
    theory = exact_coefficients(params)
    model = fit_narx([(r.x, r.y) for r in recs], EXACT_TERMS)
    assert np.all(np.abs(model.theta / theory - 1) < 1e-7)
    # Joining the records into one would create equations that straddle the seam; the
    # library must not do that (it would spoil the exact fit).
    joined = fit_narx(
        [(np.concatenate([r.x for r in recs]), np.concatenate([r.y for r in recs]))], EXACT_TERMS
    )
    assert np.max(np.abs(joined.theta / theory - 1)) > 1e-6


def test_exact_model_one_step_residuals_are_rounding_level(noise_free_record, params) -> None:
    """SPEC §2: the eight-term NARX is exact. Residuals are rounding: each prediction sums
    terms of size |a_i·y| ≤ 6·max|y|, so the error is ~ tens of eps·max|y|."""
    rec = noise_free_record
    model = exact_narx(params)
    residuals = model.residuals(rec.x, rec.y)
    predictions = model.predict(rec.x, rec.y)
    np.testing.assert_array_equal(residuals, rec.y[4:] - predictions)
    assert residuals.shape == (len(rec.y) - 4,)
    assert np.max(np.abs(residuals)) < 1000 * EPS * np.max(np.abs(rec.y))
    # And a wrong coefficient would not pass: a 1e-9 relative change of a2 is visible.
    wrong = NARX(model.terms, model.theta * np.r_[1, 1 + 1e-9, 1, 1, 1, 1, 1, 1], model.covariance)
    assert np.max(np.abs(wrong.residuals(rec.x, rec.y))) > 100 * np.max(np.abs(residuals))


def test_free_run_reproduces_noise_free_output(noise_free_record, params) -> None:
    """Free-run error is rounding fed through the model's own dynamics. Its static gain is
    1/(1 − Σa_i) ≈ 3e6 (SPEC §2: the AR part is nearly binomial), so per-step rounding of
    ~10·eps·|y| can grow to ~1e-8·|y|; the bound allows ~10× that."""
    rec = noise_free_record
    model = exact_narx(params)
    simulated = model.simulate(rec.x, rec.y)
    assert simulated.shape == rec.y.shape
    np.testing.assert_array_equal(simulated[:4], rec.y[:4])
    static_gain = 1 / (1 - np.sum(model.theta[:4]))
    assert 1e6 < static_gain < 1e7
    error = np.max(np.abs(simulated - rec.y)) / np.max(np.abs(rec.y))
    assert error < 10 * static_gain * 10 * EPS
    assert error < 1e-7


def test_free_run_of_explicit_recursion_matches_hand_loop() -> None:
    """A small model with x, cross and constant terms, checked against a plain loop."""
    terms = ["1", "y[t-1]", "y[t-2]^2", "y[t-1]*x[t-1]", "x[t]", "x[t-2]^2"]
    theta = np.array([0.01, 0.5, -0.2, 0.1, 0.3, -0.05])
    model = NARX(parse_terms(terms), theta, np.zeros((6, 6)))
    rng = np.random.default_rng(9)
    x = rng.normal(size=200)
    y0 = np.array([0.1, -0.2])
    ref = np.zeros(200)
    ref[:2] = y0
    for t in range(2, 200):
        ref[t] = (
            theta[0]
            + theta[1] * ref[t - 1]
            + theta[2] * ref[t - 2] ** 2
            + theta[3] * ref[t - 1] * x[t - 1]
            + theta[4] * x[t]
            + theta[5] * x[t - 2] ** 2
        )
    np.testing.assert_allclose(model.simulate(x, y0), ref, rtol=1e-13, atol=1e-15)


def test_free_run_with_friction_damping_and_a_sinusoid_matches_hand_loop() -> None:
    """Non-polynomial factors in the recursion: sign and abs of the output's difference, a
    sinusoid of the sample index (from t0), and a difference of the input."""
    terms = ["y[t-1]", "y[t-2]", "sign(dy[t-1])", "dy[t-2]*abs(dy[t-2])", "sin(2pi*0.03*t)", "abs(dx[t-1])"]
    theta = np.array([1.2, -0.5, -0.01, -0.3, 0.02, 0.05])
    model = NARX(parse_terms(terms), theta, np.zeros((6, 6)))
    x = np.random.default_rng(10).normal(size=300)
    y0 = np.array([0.1, -0.2, 0.05])
    t0 = 11
    ref = np.zeros(300)
    ref[:3] = y0
    for t in range(3, 300):
        d1, d2 = ref[t - 1] - ref[t - 2], ref[t - 2] - ref[t - 3]
        ref[t] = (
            theta[0] * ref[t - 1]
            + theta[1] * ref[t - 2]
            + theta[2] * np.sign(d1)
            + theta[3] * d2 * abs(d2)
            + theta[4] * np.sin(2 * np.pi * 0.03 * (t0 + t))
            + theta[5] * abs(x[t - 1] - x[t - 2])
        )
    simulated = model.simulate(x, y0, t0=t0)
    np.testing.assert_allclose(simulated, ref, rtol=1e-12, atol=1e-15)
    # One-step predictions on the simulated output reproduce it: the same model, two code paths.
    np.testing.assert_allclose(model.predict(x, simulated, t0=t0), simulated[3:], rtol=1e-12, atol=1e-15)


def test_free_run_of_diverging_model_yields_nan_from_blow_up() -> None:
    model = NARX(parse_terms(["y[t-1]^2"]), np.array([2.0]), np.zeros((1, 1)))
    out = model.simulate(np.zeros(50), [3.0])
    assert np.all(np.isfinite(out[:5]))
    assert np.isnan(out[-1])
    first_nan = int(np.argmax(np.isnan(out)))
    assert np.all(np.isnan(out[first_nan:]))
    with pytest.raises(InputError, match="needs 1 initial output samples, got 0"):
        model.simulate(np.zeros(5), [])


def test_document_round_trip_is_exact_and_json(disturbed_record) -> None:
    model = fit_narx([(disturbed_record.x, disturbed_record.y)], [*EXACT_TERMS, "y[t-1]*x[t-2]", "1"])
    document = model.to_document()
    text = json.dumps(document)
    for restored in (NARX.from_document(document), NARX.from_document(json.loads(text))):
        assert restored.terms == model.terms
        np.testing.assert_array_equal(restored.theta, model.theta)
        np.testing.assert_array_equal(restored.covariance, model.covariance)
        assert restored.sigma2 == model.sigma2
        assert restored.n_obs == model.n_obs
    assert document["kind"] == "narx"
    assert document["terms"][-2:] == ["y[t-1]*x[t-2]", "1"]


def test_document_refusals() -> None:
    document = NARX(EXACT_TERMS, np.ones(8), np.eye(8)).to_document()
    with pytest.raises(InputError, match="not a narx model document"):
        NARX.from_document({**document, "kind": "fnarx"})
    with pytest.raises(InputError, match="schema version 99"):
        NARX.from_document({**document, "schema_version": 99})
    with pytest.raises(InputError, match="do not match the terms"):
        NARX.from_document({**document, "theta": [1.0] * 7})


@pytest.fixture(scope="module")
def short_record():
    rec = simulate(Scenario(disturbance_std=DISTURBANCE_STD), 200, seed=41)
    return rec.x.copy(), rec.y.copy()


@pytest.mark.parametrize(
    ("mutate", "fragment"),
    [
        (
            lambda x, y: (x, np.r_[y[:50], np.nan, y[51:]]),
            "y has 1 NaN or infinite value(s), first at sample 50",
        ),
        (
            lambda x, y: (np.r_[x[:7], np.inf, x[8:]], y),
            "x has 1 NaN or infinite value(s), first at sample 7",
        ),
        (lambda x, y: (x[:-1], y), "x has 199 samples but y has 200"),
        (lambda x, y: (x[:12], y[:12]), "12 samples is too short; this needs at least 13"),
        (lambda x, y: (np.full_like(x, 3.0), y), "x is constant"),
        (lambda x, y: (x, np.zeros_like(y)), "y is constant"),
        (lambda x, y: (x.reshape(20, 10), y.reshape(20, 10)), "must be one-dimensional"),
        (lambda x, y: (["a"] * 200, y), "signals must be numbers"),
    ],
)
def test_bad_records_raise_input_error(short_record, mutate, fragment) -> None:
    x, y = mutate(*short_record)
    with pytest.raises(InputError) as info:
        fit_narx([(x, y)], EXACT_TERMS)
    assert fragment in str(info.value)


def test_bad_record_is_named_by_position(short_record) -> None:
    x, y = short_record
    with pytest.raises(InputError, match="record 2: y has 1 NaN"):
        fit_narx([(x, y), (x, np.r_[np.nan, y[1:]])], EXACT_TERMS)
    with pytest.raises(InputError, match="at least one record"):
        fit_narx([], EXACT_TERMS)


def test_predict_and_residuals_validate_records(short_record, params) -> None:
    x, y = short_record
    model = exact_narx(params)
    with pytest.raises(InputError, match="NaN"):
        model.predict(x, np.r_[y[:-1], np.nan])
    with pytest.raises(InputError, match="too short"):
        model.residuals(x[:4], y[:4])


def test_values_whose_cubic_sums_overflow_are_refused_before_fitting(disturbed_record) -> None:
    """y·1e60 fits a linear term's sums but not a cubic one's (y⁶·N overflows): the refusal
    names the overflow and the degree, not the singular matrix the overflow would leave."""
    scaled = (disturbed_record.x, disturbed_record.y * 1e60)
    with pytest.raises(InputError, match=r"degree 3 the statistics overflow"):
        fit_narx([scaled], EXACT_TERMS)
    linear = fit_narx([scaled], ["y[t-1]", "y[t-2]", "x[t-4]"])  # degree 1: within the bound
    assert np.all(np.isfinite(linear.theta))
