"""Functionally pooled models (models/pooled.py) against theory, an independent computation and
the simulator's temperature-dependent stiffness."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import DISTURBANCE_STD, exact_narx_residual, exact_regressors, scaled_lstsq
from scipy import stats

from models.errors import InputError
from models.inspection import inspect
from models.narx import fit_narx
from models.pooled import (
    PooledExperiment,
    PooledModel,
    check_baseline,
    fit_pooled,
    inspect_pooled,
    tensor_values,
)
from simulator.physics import PhysicalParameters
from simulator.simulate import Scenario, simulate
from simulator.temperature import Thermal
from simulator.theory import EXACT_TERMS, exact_coefficients, exact_narx

NARX_TERMS = ["y[t-1]", "y[t-2]", "x[t-1]", "y[t-1]^3"]
T_LOW, T_HIGH = -10.0, 30.0
TRAINING_TEMPERATURES = np.linspace(T_LOW, T_HIGH, 9)
NOISE = 0.5
N = 2000


def narx_coefficients(T: float, degree: int, level: float | None = None) -> np.ndarray:
    """a1, a2, b, c of y[t] = a1·y[t−1] + a2·y[t−2] + b·x[t−1] + c·y³[t−1] + e[t], polynomials of
    ``degree`` in the temperature T [°C] and, given a ``level`` s (an excitation level, 1 … 4),
    affine in s with a T·s cross term. Over these ranges |y| stays below 12, where the map's
    slope a1 + 3c·y² stays inside (−1, 1.5): stable."""
    d = T - 10.0
    a1 = 1.2 + 0.004 * d + (3e-4 * d**2 if degree == 2 else 0.0)
    a2, b = -0.6 - 0.002 * d, 1.0 + 0.01 * d
    if level is not None:
        a2 += 5e-4 * d * (level - 2.5)
        b += 0.1 * (level - 2.5)
    return np.array([a1, a2, b, -0.002 - 5e-5 * d])


def narx_record(coefficients: np.ndarray, seed: int, n: int = N) -> tuple[np.ndarray, np.ndarray]:
    """The recursion of :func:`narx_coefficients` driven by white x and e (std NOISE); 500
    samples of start-up dropped."""
    a1, a2, b, c = coefficients.tolist()
    rng = np.random.default_rng(seed)
    x = rng.normal(size=n + 500)
    e = rng.normal(scale=NOISE, size=n + 500).tolist()
    drive = x.tolist()
    y = [0.0, 0.0]
    for t in range(2, n + 500):
        y.append(a1 * y[t - 1] + a2 * y[t - 2] + b * drive[t - 1] + c * y[t - 1] ** 3 + e[t])
    return x[500:], np.array(y[500:])


def narx_experiments(degree: int, seed0: int) -> list[PooledExperiment]:
    return [
        PooledExperiment(*narx_record(narx_coefficients(T, degree), seed0 + i), {"temperature": float(T)})
        for i, T in enumerate(TRAINING_TEMPERATURES)
    ]


def chebyshev2(T: float, size: int) -> np.ndarray:
    """U_0 … U_{size−1} of u = (2T − 30 + 10)/40, written out (SPEC §4), independent of models.basis."""
    u = (2 * T - T_HIGH - T_LOW) / (T_HIGH - T_LOW)
    return np.array([1.0, 2 * u, 4 * u**2 - 1, 8 * u**3 - 4 * u, 16 * u**4 - 12 * u**2 + 1])[:size]


@pytest.fixture(scope="module", params=[1, 2])
def narx_case(request) -> tuple[int, PooledModel, list[PooledExperiment]]:
    degree = request.param
    runs = narx_experiments(degree, seed0=100 * degree)
    return degree, fit_pooled(runs, NARX_TERMS), runs


# ---------------------------------------------------------------- theory


def test_criterion_picks_the_true_degree(narx_case) -> None:
    """BIC over degrees 0 … 4: an extra degree adds 4 parameters, a penalty 4·ln(17 982) = 39.2
    that a χ²(4) exceeds with probability 1e-7; a missing one leaves a1 off by up to 0.12."""
    degree, model, _ = narx_case
    assert model.degrees == {"temperature": degree}
    assert [row.degrees for row in model.criterion] == [(d,) for d in range(5)]
    n = model.n_obs
    for row in model.criterion:
        assert row.parameters == 4 * (row.degrees[0] + 1)
        assert row.bic == pytest.approx(n * np.log(row.sigma2) + row.parameters * np.log(n), rel=1e-12)
    assert min(model.criterion, key=lambda row: row.bic).degrees == (degree,)


def test_coefficients_recovered_within_their_covariance(narx_case) -> None:
    """θ̂ − θ ~ N(0, Cov) for the exact projection coefficients θ (the true polynomials written
    on U_0 … U_d by solving at d + 1 temperatures), so (θ̂ − θ)ᵀCov⁻¹(θ̂ − θ) ~ χ²(4(d + 1));
    tested at its 0.999 quantile. And at every temperature each coefficient within 4 se."""
    degree, model, _ = narx_case
    size = degree + 1
    nodes = np.linspace(T_LOW, T_HIGH, size)
    U = np.array([chebyshev2(T, size) for T in nodes])
    exact = np.linalg.solve(U, np.array([narx_coefficients(T, degree) for T in nodes])).T
    d = (model.theta - exact).ravel()
    assert d @ np.linalg.solve(model.covariance, d) < stats.chi2.ppf(0.999, df=4 * size)
    for T in (-10.0, -3.3, 10.0, 24.0, 30.0):
        narx = model.narx_at({"temperature": T})
        z = (narx.theta - narx_coefficients(T, degree)) / narx.standard_errors()
        assert np.all(np.abs(z) < 4), (T, z)


def test_compressed_fit_is_the_stacked_ols(narx_case) -> None:
    """The per-experiment QR compression gives the OLS of the whole stacked Kronecker design,
    computed here directly by numpy's SVD solver: θ, σ̂²_m and σ̂²(XᵀX)⁻¹."""
    degree, model, runs = narx_case
    size = degree + 1
    rows, targets = [], []
    for run in runs:
        x, y = np.asarray(run.x), np.asarray(run.y)
        Phi = np.column_stack([y[1:-1], y[:-2], x[1:-1], y[1:-1] ** 3])
        g = chebyshev2(run.conditions["temperature"], size)
        rows.append(np.einsum("ti,j->tij", Phi, g).reshape(len(Phi), -1))
        targets.append(y[2:])
    X, Y = np.vstack(rows), np.concatenate(targets)
    theta = scaled_lstsq(X, Y)
    np.testing.assert_allclose(model.theta.ravel(), theta, rtol=1e-9, atol=1e-12)
    residuals = Y - X @ theta
    per_run = [np.mean(e**2) for e in np.split(residuals, len(runs))]
    np.testing.assert_allclose(model.experiment_sigma2, per_run, rtol=1e-9)
    covariance = np.mean(residuals**2) * np.linalg.inv(X.T @ X)
    np.testing.assert_allclose(model.covariance, covariance, rtol=1e-7, atol=1e-14)
    assert model.n_obs == len(Y)


def test_two_operating_variables() -> None:
    """Temperature and an excitation level s on a 4 × 4 grid: b is affine in s and a2 carries a
    T·s term, so the truth has degree (1, 1), whose tensor basis [1, 2u_s, 2u_T, 4u_T·u_s]
    (the last argument fastest) holds the cross term. BIC picks it (an extra degree adds 8
    parameters, a penalty of 83 a χ²(8) exceeds with probability 1e-14), and θ̂ lies within its
    covariance of the truth."""
    grid = [(T, s) for T in np.linspace(T_LOW, T_HIGH, 4) for s in (1.0, 2.0, 3.0, 4.0)]
    runs = [
        PooledExperiment(*narx_record(narx_coefficients(T, 1, s), 500 + i), {"temperature": T, "level": s})
        for i, (T, s) in enumerate(grid)
    ]
    model = fit_pooled(runs, NARX_TERMS, variables=["temperature", "level"])
    assert model.arguments == ("temperature", "level")
    assert model.degrees == {"temperature": 1, "level": 1}
    assert all(np.prod(np.add(row.degrees, 1)) < 16 for row in model.criterion)

    def g(T: float, s: float) -> np.ndarray:
        u_T, u_s = (2 * T - T_HIGH - T_LOW) / (T_HIGH - T_LOW), (2 * s - 5) / 3
        return np.array([1.0, 2 * u_s, 2 * u_T, 4 * u_T * u_s])

    corners = [(T_LOW, 1.0), (T_LOW, 4.0), (T_HIGH, 1.0), (T_HIGH, 4.0)]
    G = np.array([g(*corner) for corner in corners])
    exact = np.linalg.solve(G, np.array([narx_coefficients(T, 1, s) for T, s in corners])).T
    d = (model.theta - exact).ravel()
    assert d @ np.linalg.solve(model.covariance, d) < stats.chi2.ppf(0.999, df=16)
    np.testing.assert_allclose(
        model.narx_at({"temperature": 2.0, "level": 3.5}).theta, model.theta @ g(2.0, 3.5)
    )
    with pytest.raises(InputError, match=r"'level' = 4.5 lies outside the range \[1, 4\]"):
        model.narx_at({"temperature": 2.0, "level": 4.5})


def test_residual_variance_model(narx_case) -> None:
    """σ² is 0.25 at every temperature: ln σ̂²(w) lies within 4 of its standard errors
    √(2/ν_0) of ln 0.25."""
    _, model, _ = narx_case
    for T in (-10.0, 5.0, 30.0):
        sigma2, dof = model.variance_at({"temperature": T})
        assert abs(np.log(sigma2 / NOISE**2)) < 4 * np.sqrt(2 / dof)


def test_residual_variance_model_by_hand(narx_case) -> None:
    """With degree 0 the weighted fit of ln σ̂²_m (weights N_m/2, all equal here) is their mean,
    taken of the unbiased σ̂²_m·n/(n − n_θ); its variance 2/Σ N_m is scaled by the reduced χ²
    Σ (N_m/2)·(ℓ_m − ℓ̄)²/(M − 1) when that exceeds 1."""
    _, _, runs = narx_case
    model = fit_pooled(runs, NARX_TERMS, degrees={"temperature": 0})
    n, lengths = model.n_obs, np.full(len(runs), model.n_obs // len(runs))
    logs = np.log(model.experiment_sigma2 * n / (n - 4))
    chi2 = np.sum(lengths / 2 * (logs - logs.mean()) ** 2) / (len(runs) - 1)
    sigma2, dof = model.variance_at({"temperature": 17.0})
    assert sigma2 == pytest.approx(np.exp(logs.mean()), rel=1e-12)
    assert dof == pytest.approx(n / max(1.0, chi2), rel=1e-9)


def test_document_round_trip(narx_case) -> None:
    _, model, _ = narx_case
    document = json.loads(json.dumps(model.to_document()))
    assert document["kind"] == "pooled" and document["schema_version"] == 1
    back = PooledModel.from_document(document)
    assert back.name == model.name and back.terms == model.terms and back.arguments == model.arguments
    assert back.bases == model.bases and back.criterion == model.criterion and back.n_obs == model.n_obs
    for field in ("theta", "covariance", "log_variance", "log_variance_covariance", "experiment_arguments"):
        np.testing.assert_array_equal(getattr(back, field), getattr(model, field))
    at = {"temperature": 7.5}
    np.testing.assert_array_equal(back.narx_at(at).theta, model.narx_at(at).theta)
    assert back.variance_at(at) == model.variance_at(at)


def test_document_refusals(narx_case) -> None:
    _, model, _ = narx_case
    document = model.to_document()
    with pytest.raises(InputError, match="not a pooled model document"):
        PooledModel.from_document({**document, "kind": "fnarx"})
    with pytest.raises(InputError, match="schema version 2"):
        PooledModel.from_document({**document, "schema_version": 2})
    with pytest.raises(InputError, match="theta has shape"):
        PooledModel.from_document({**document, "theta": document["theta"][:-1]})
    with pytest.raises(InputError, match="pooled model document"):
        PooledModel.from_document({key: value for key, value in document.items() if key != "covariance"})


# ---------------------------------------------------------------- simulator: temperature


def train_pooled_baseline(seed0: int) -> PooledModel:
    """Nine 2000-sample healthy experiments at −10, −5, …, 30 °C."""
    runs = []
    for i, T in enumerate(TRAINING_TEMPERATURES):
        rec = simulate(Scenario(disturbance_std=DISTURBANCE_STD, temperature=float(T)), N, seed=seed0 + i)
        runs.append(PooledExperiment(rec.x, rec.y, {"temperature": float(T)}))
    return fit_pooled(runs, EXACT_TERMS)


@pytest.fixture(scope="module")
def pooled_baseline() -> PooledModel:
    return train_pooled_baseline(2000)


def healthy(T: float, seed: int):
    return simulate(Scenario(disturbance_std=DISTURBANCE_STD, temperature=T), N, seed=seed)


def test_pooled_baseline_follows_the_exact_narx(pooled_baseline) -> None:
    """Every spring k(T) = k·(1 − 0.005·(T − 20)): the exact NARX (SPEC §2 at those stiffnesses)
    lies within 4 standard errors of the pooled baseline at each temperature."""
    for T in (-10.0, 3.0, 20.0, 30.0):
        narx = pooled_baseline.narx_at({"temperature": T})
        exact = exact_coefficients(PhysicalParameters().at_temperature(T, Thermal()))
        assert np.all(np.abs((narx.theta - exact) / narx.standard_errors()) < 4), T


def test_one_temperature_baseline_alarms_where_the_pooled_one_does_not() -> None:
    """40 healthy records at temperatures drawn uniformly over −10 … 30 °C. The baseline of
    today, one NARX trained on 18 000 samples at 20 °C, raises an alarm on most (every record
    at −10 °C, its springs 15 % stiffer, or +30 °C, 5 % softer). The pooled baseline's test
    has size α over the training data too (its reference variance carries its own estimation
    error), so four pooled baselines, each trained anew and judging ten records, make 40
    nearly independent trials: their false alarms stay below the 0.999 quantile of
    Binomial(40, α). (One model judging all 40 would share its error of σ̂²(w), about half the
    record's own standard error, among them.)"""
    rec = simulate(Scenario(disturbance_std=DISTURBANCE_STD, temperature=20.0), 9 * N, seed=2100)
    one_temperature = fit_narx([(rec.x, rec.y)], EXACT_TERMS)
    for index, T in enumerate((T_LOW, T_LOW, T_HIGH, T_HIGH)):
        record = healthy(T, 2200 + index)
        assert check_baseline(one_temperature, record.x, record.y).fault_detected, T
    temperatures = np.random.default_rng(2300).uniform(T_LOW, T_HIGH, 40)
    alarms_one = alarms_pooled = 0
    for index, T in enumerate(temperatures):
        if index % 10 == 0:
            pooled_baseline = train_pooled_baseline(3000 + index)
        record = healthy(float(T), 2400 + index)
        alarms_one += check_baseline(one_temperature, record.x, record.y).fault_detected
        pooled = check_baseline(pooled_baseline, record.x, record.y, {"temperature": float(T)})
        alarms_pooled += pooled.fault_detected
        assert pooled.conditions == {"temperature": float(T)}
    assert alarms_one >= 20, alarms_one
    assert alarms_pooled <= stats.binom.ppf(0.999, 40, 0.05), alarms_pooled


def test_check_baseline_figures(pooled_baseline) -> None:
    """The check's figures are those of the tests it names: F = mean(e²)/(σ̂²(w) + mean φᵀCφ)
    against F(N − 4, ν_0) at α_F = 1 − 0.95/0.999, Ljung–Box at α_Q = 0.001."""
    record = healthy(12.0, 2500)
    check = check_baseline(pooled_baseline, record.x, record.y, {"temperature": 12.0, "wind": 3.0})
    narx = pooled_baseline.narx_at({"temperature": 12.0})
    residuals = exact_narx_residual(record.x, record.y, narx.theta)
    np.testing.assert_allclose(check.residuals, residuals, rtol=1e-9, atol=1e-15)
    sigma2, dof = pooled_baseline.variance_at({"temperature": 12.0})
    Phi, _ = exact_regressors(record.x, record.y)
    estimation = np.mean([phi @ narx.covariance @ phi for phi in Phi])
    assert 0 < estimation < 0.01 * sigma2
    assert check.reference_sigma2 == pytest.approx(sigma2 + estimation, rel=1e-9)
    assert check.variance_ratio == pytest.approx(np.mean(residuals**2) / (sigma2 + estimation), rel=1e-9)
    assert check.reference_dof == pytest.approx(dof)
    # A plain NARX is its own reference: σ̂²·n/(n − 8) on n_obs degrees of freedom.
    plain = check_baseline(narx, record.x, record.y)
    assert plain.reference_sigma2 == pytest.approx(
        narx.sigma2 * narx.n_obs / (narx.n_obs - 8) + estimation, rel=1e-9
    )
    assert plain.reference_dof == narx.n_obs
    with pytest.raises(InputError, match="no residual variance to test against"):
        check_baseline(exact_narx(PhysicalParameters()), record.x, record.y)
    assert check.variance_critical == pytest.approx(stats.f.ppf(0.95 / 0.999, N - 4, dof), rel=1e-9)
    assert check.q_critical == pytest.approx(stats.chi2.ppf(0.999, 39), rel=1e-9)
    assert check.fault_detected == (
        check.variance_ratio > check.variance_critical or check.q > check.q_critical
    )


def test_pooled_baseline_detects_a_three_percent_k2_fault(pooled_baseline) -> None:
    """A 3 % loosening of k2 moves a2 by ~1.4e-4 (SPEC §2: 1.5e-3 at 32 %), tens of its
    standard errors: flagged at each of five temperatures."""
    for index, T in enumerate((-8.0, 0.0, 10.0, 20.0, 29.0)):
        record = simulate(
            Scenario(fault="k2", k=3.0, disturbance_std=DISTURBANCE_STD, temperature=T), N, seed=2600 + index
        )
        assert check_baseline(pooled_baseline, record.x, record.y, {"temperature": T}).fault_detected, T


@pytest.fixture(scope="module")
def pooled_k2() -> PooledModel:
    runs = []
    for i, (T, k) in enumerate(
        (T, k) for T in (-10.0, 0.0, 10.0, 20.0, 30.0) for k in (-8.0, -4.0, 0.0, 4.0, 8.0)
    ):
        rec = simulate(
            Scenario(fault="k2", k=k, disturbance_std=DISTURBANCE_STD, temperature=T), N, seed=2700 + i
        )
        runs.append(PooledExperiment(rec.x, rec.y, {"temperature": T}, k))
    return fit_pooled(runs, EXACT_TERMS, name="k2")


def test_pooled_fault_mode_estimates_k_at_each_temperature(pooled_k2) -> None:
    """Pooled over (T, k) from a 5 × 5 grid; every coefficient is affine in k2 (SPEC §2), so the
    criterion takes degree 1 in k. A 3 % k2 fault at −5, 12 and 27 °C: detected, localised,
    and the 99.9 % interval covers 3."""
    assert pooled_k2.arguments == ("temperature", "k") and pooled_k2.degrees["k"] == 1
    for index, T in enumerate((-5.0, 12.0, 27.0)):
        record = simulate(
            Scenario(fault="k2", k=3.0, disturbance_std=DISTURBANCE_STD, temperature=T), N, seed=2800 + index
        )
        verdict = inspect_pooled(record.x, record.y, {"temperature": T}, [pooled_k2], alpha=1e-3)
        assert (verdict.status, verdict.fault_mode) == ("faulty", "k2"), T
        low, high = verdict.interval
        assert low < 3.0 < high, (T, verdict.interval)
        assert verdict == inspect(record.x, record.y, [pooled_k2.fnarx_at({"temperature": T})], alpha=1e-3)


def test_fault_mode_at_conditions_is_the_tensor_model(pooled_k2) -> None:
    """fnarx_at(w) at magnitude k gives θ(w, k) = Θ·(g_T(w) ⊗ g_k(k)) and its covariance
    (I ⊗ g)ᵀ·Cov·(I ⊗ g), computed here from the full tensor basis."""
    for T, k in ((-10.0, 8.0), (4.2, -1.5), (30.0, 3.0)):
        fnarx = pooled_k2.fnarx_at({"temperature": T})
        g = np.kron(pooled_k2.bases[0].values(T), pooled_k2.bases[1].values(k))
        np.testing.assert_allclose(tensor_values(pooled_k2.bases, [T, k]), g, rtol=1e-14)
        np.testing.assert_allclose(fnarx.coefficients(k), pooled_k2.theta @ g, rtol=1e-12)
        J = np.kron(np.eye(len(EXACT_TERMS)), g)
        np.testing.assert_allclose(
            fnarx.coefficient_covariance(k), J @ pooled_k2.covariance @ J.T, rtol=1e-9, atol=1e-40
        )


# ---------------------------------------------------------------- refusals


@pytest.fixture(scope="module")
def small_runs() -> list[PooledExperiment]:
    return [
        PooledExperiment(
            *narx_record(narx_coefficients(T, 1), 900 + i, n=400), {"temperature": T, "speed": 1.0 + i}
        )
        for i, T in enumerate((-10.0, 0.0, 10.0, 20.0, 30.0))
    ]


def test_refuses_records_outside_the_trained_range(narx_case) -> None:
    """Within 1 % of the 40 °C span (0.4 °C) beyond an end a record is evaluated; beyond, refused."""
    _, model, _ = narx_case
    assert model.ranges == {"temperature": (T_LOW, T_HIGH)}
    model.narx_at({"temperature": 30.3})
    model.narx_at({"temperature": -10.3})
    for T in (30.5, -11.0, 45.0):
        with pytest.raises(InputError, match=rf"'temperature' = {T:g} lies outside the range \[-10, 30\]"):
            model.narx_at({"temperature": T})
    x, y = narx_record(narx_coefficients(45.0, 1), 1)
    with pytest.raises(InputError, match="outside the range"):
        check_baseline(model, x, y, {"temperature": 45.0})
    for bad in (float("nan"), "warm", None):
        with pytest.raises(InputError, match="'temperature' must be a"):
            model.narx_at({"temperature": bad})


def test_refuses_records_missing_a_variable(narx_case) -> None:
    _, model, _ = narx_case
    x, y = narx_record(narx_coefficients(10.0, 1), 2)
    with pytest.raises(
        InputError,
        match=r"needs operating variable 'temperature' \(trained over \[-10, 30\]\); "
        "the record carries speed",
    ):
        check_baseline(model, x, y, {"speed": 3.0})
    with pytest.raises(InputError, match=r"needs operating variable 'temperature'.*carries none"):
        check_baseline(model, x, y)


def test_refuses_training_at_one_condition(small_runs) -> None:
    same = [PooledExperiment(r.x, r.y, {"temperature": 20.0}) for r in small_runs]
    with pytest.raises(InputError, match="every experiment has operating variable 'temperature' = 20"):
        fit_pooled(same, NARX_TERMS)
    at_one_k = [PooledExperiment(r.x, r.y, r.conditions, 5.0) for r in small_runs]
    with pytest.raises(InputError, match="every experiment has fault magnitude 'k' = 5"):
        fit_pooled(at_one_k, NARX_TERMS, name="k2", variables=["temperature"])


def test_refuses_unknown_or_missing_variable_names(small_runs) -> None:
    with pytest.raises(InputError, match=r"unknown operating variable 'humidity'.*carry speed, temperature"):
        fit_pooled(small_runs, NARX_TERMS, variables=["temperature", "humidity"])
    with pytest.raises(InputError, match="'k' names the fault magnitude"):
        fit_pooled(small_runs, NARX_TERMS, variables=["k"])
    partial = [*small_runs[:-1], PooledExperiment(small_runs[-1].x, small_runs[-1].y, {"speed": 2.0})]
    with pytest.raises(InputError, match="experiment 5 carries no operating variable 'temperature'"):
        fit_pooled(partial, NARX_TERMS, variables=["temperature"])
    with pytest.raises(InputError, match="at least one operating variable"):
        fit_pooled([PooledExperiment(r.x, r.y, {}) for r in small_runs], NARX_TERMS)
    bad = [
        *small_runs[:-1],
        PooledExperiment(small_runs[-1].x, small_runs[-1].y, {"temperature": float("inf")}),
    ]
    with pytest.raises(InputError, match="experiment 5: operating variable 'temperature' must be a finite"):
        fit_pooled(bad, NARX_TERMS, variables=["temperature"])


def test_refuses_bad_settings(small_runs) -> None:
    mixed = [PooledExperiment(r.x, r.y, r.conditions, 1.0 * i) for i, r in enumerate(small_runs[:-1])]
    with pytest.raises(InputError, match="experiment 5 has no fault magnitude k"):
        fit_pooled([*mixed, small_runs[-1]], NARX_TERMS, name="k2")
    with pytest.raises(InputError, match="max_degree must be a whole number from 0 to 4"):
        fit_pooled(small_runs, NARX_TERMS, max_degree=5)
    with pytest.raises(
        InputError, match="degrees must name each of speed, temperature once; got temperature"
    ):
        fit_pooled(small_runs, NARX_TERMS, degrees={"temperature": 1})
    with pytest.raises(
        InputError, match=r"make 25 basis functions, which need more than 25 experiments.*there are 5"
    ):
        fit_pooled(small_runs, NARX_TERMS, degrees={"temperature": 4, "speed": 4})
    with pytest.raises(InputError, match="a pooled model needs experiments"):
        fit_pooled([], NARX_TERMS)
    model = fit_pooled(small_runs, NARX_TERMS, degrees={"temperature": 1, "speed": 0})
    assert model.degrees == {"speed": 0, "temperature": 1} and len(model.criterion) == 1
    with pytest.raises(InputError, match="is a pooled baseline; evaluate it with narx_at"):
        model.fnarx_at({"temperature": 0.0, "speed": 2.0})
    faulty = fit_pooled(
        mixed, NARX_TERMS, name="k2", variables=["temperature"], degrees={"temperature": 1, "k": 0}
    )
    with pytest.raises(InputError, match="'k2' is a pooled fault mode; evaluate it with fnarx_at"):
        faulty.narx_at({"temperature": 0.0})


def test_pooled_fault_mode_refuses_records_it_cannot_judge(pooled_k2) -> None:
    record = simulate(
        Scenario(fault="k2", k=3.0, disturbance_std=DISTURBANCE_STD, temperature=35.0), N, seed=2900
    )
    with pytest.raises(InputError, match=r"'temperature' = 35 lies outside the range \[-10, 30\].*'k2'"):
        inspect_pooled(record.x, record.y, {"temperature": 35.0}, [pooled_k2])
    with pytest.raises(InputError, match="'k2' needs operating variable 'temperature'"):
        inspect_pooled(record.x, record.y, {"humidity": 0.6}, [pooled_k2])
    with pytest.raises(InputError, match="its variance depends on k too"):
        pooled_k2.variance_at({"temperature": 10.0})
