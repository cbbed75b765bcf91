"""Vector fault-mode models on the 5-mass chain: the fit against the scheme's own matrices, the
localisation with five sensors against one, and the refusals (models.vector)."""

from __future__ import annotations

import numpy as np
import pytest

from models.errors import InputError
from models.vector import fit_vector_fnarx, inspect_vector, regressors
from simulator.chain import ChainParameters, ChainScenario, simulate_chain
from simulator.options import DAMPING, MASS, STIFFNESS

CHAIN = ChainParameters.build(5, [MASS], [STIFFNESS], [DAMPING])
SPRINGS = CHAIN.springs[:5]
TRAINING_K = (-8.0, -4.0, 0.0, 4.0, 8.0)


def record(fault: str, k: float, seed: int, noise: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    scenario = ChainScenario(CHAIN, fault, k, disturbance_std=800.0, y_noise_std=noise)
    simulated = simulate_chain(scenario, 2000, seed)
    return simulated.x, np.column_stack([simulated.responses[f"y{m}"] for m in range(1, 6)])


def experiments(
    spring: str, channels: slice, noise: float = 1e-6
) -> list[tuple[np.ndarray, np.ndarray, float]]:
    index = SPRINGS.index(spring)
    out = []
    for j, k in enumerate(TRAINING_K):
        x, y = record(spring, k, 1000 + 10 * index + j, noise)
        out.append((x, y[:, channels], k))
    return out


def test_the_fit_recovers_the_schemes_matrices_where_no_noise_enters():
    """y[t] = A1(k)·y[t−1] + A0(k)·y[t−2] + (Ts²/m1)·e1·x[t−2] + (Ts²/m1)·e1·w[t−2] exactly
    (simulator.chain's recursion), A0 affine in k3: with no sensor noise the equations of masses
    2 … 5 carry no error at all and their fitted coefficients are the scheme's at every k."""
    model = fit_vector_fnarx("k3", experiments("k3", slice(0, 5), noise=0.0), lags=2)
    for k in (-6.0, 0.0, 5.0):
        coefficients = np.tensordot(
            model.basis.values(k), model.theta.reshape(-1, model.basis.size, 5), axes=([0], [1])
        )
        A1, A0 = CHAIN.with_fault("k3", k).recursion()
        fitted_A1, fitted_A0 = coefficients[:5].T, coefficients[5:10].T
        np.testing.assert_allclose(fitted_A1[1:], A1[1:], atol=1e-9)
        np.testing.assert_allclose(fitted_A0[1:], A0[1:], atol=1e-9)
        # The input reaches mass 1 alone, two samples late. Mass 1's equation carries the
        # disturbance: its coefficient's standard error is about (800 N / 25 kN)/√10 000 = 3·10⁻⁴
        # of its value, so 10⁻³ is three of them.
        np.testing.assert_allclose(coefficients[10:, 1:], 0.0, atol=1e-12)
        assert coefficients[11, 0] == pytest.approx(CHAIN.ts**2 / MASS, rel=1e-3)


def test_five_sensors_localise_what_one_cannot():
    """The study of bench/vector_localisation.py at a tenth of its size
    (docs/explanation/vector-models.md: 250/250 with all
    five sensors, 40/250 with mass 1 alone): 20 records, k uniform over 3 … 8 %."""
    everything = [fit_vector_fnarx(s, experiments(s, slice(0, 5)), lags=2) for s in SPRINGS]
    alone = [fit_vector_fnarx(s, experiments(s, slice(0, 1)), lags=10) for s in SPRINGS]
    rng = np.random.default_rng(11)
    right_all = right_one = 0
    for i in range(20):
        spring, k = SPRINGS[i % 5], float(rng.uniform(3.0, 8.0))
        x, y = record(spring, k, 7000 + i)
        verdict = inspect_vector(x, y, everything)
        right_all += verdict.localised == spring
        right_one += inspect_vector(x, y[:, :1], alone).localised == spring
        mode = next(m for m in verdict.modes if m.name == spring)
        assert abs(mode.k_hat - k) < 4 * mode.sigma_k, (spring, k, mode)
        assert len(mode.channel_rms) == 5 and mode.whiteness.channels == 5
    assert right_all >= 19, right_all
    assert right_one <= 10, right_one


def test_regressors_are_every_channels_lags_then_the_inputs():
    x = np.arange(6.0)
    y = np.column_stack([10 + np.arange(6.0), 20 + np.arange(6.0)])
    phi = regressors(x, y, 2)
    # Row for t = 2: y[1] (both channels), y[0] (both), x[1], x[0].
    np.testing.assert_array_equal(phi[0], [11, 21, 10, 20, 1, 0])


def test_bad_input_is_refused():
    x, y = record("k2", 0.0, 1)
    with pytest.raises(InputError, match="same fault magnitude"):
        fit_vector_fnarx("k2", [(x, y, 4.0), (x, y, 4.0)])
    with pytest.raises(InputError, match="same response channels"):
        fit_vector_fnarx("k2", [(x, y, 0.0), (x, y[:, :3], 4.0)])
    model = fit_vector_fnarx("k2", [(x, y, 0.0), (*record("k2", 8.0, 2), 8.0)])
    with pytest.raises(InputError, match="judges 5 response channels; the record has 4"):
        inspect_vector(x, y[:, :4], [model])
    with pytest.raises(InputError, match="too short"):
        inspect_vector(x[:4], y[:4], [model])
    with pytest.raises(InputError, match="not finite"):
        inspect_vector(x, np.where(np.arange(2000)[:, None] == 7, np.nan, y), [model])


def test_the_models_poles_and_free_run_are_the_schemes():
    """Fitted without noise, the model at k = 4 % runs free exactly as the chain does, and its
    modal parameters are the eigenvalues of the scheme's own transition matrix [[0, I], [A0, A1]]."""
    from models.vector import modal_parameters, simulate_vector

    def clean(k: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        simulated = simulate_chain(ChainScenario(CHAIN, "k2", k), 2000, seed)
        return simulated.x, np.column_stack([simulated.responses[f"y{m}"] for m in range(1, 6)])

    model = fit_vector_fnarx("k2", [(*clean(k, 20 + i), k) for i, k in enumerate(TRAINING_K)], lags=2)
    A1, A0 = CHAIN.with_fault("k2", 4.0).recursion()
    transition = np.block([[np.zeros((5, 5)), np.eye(5)], [A0, A1]])
    poles = np.linalg.eigvals(transition)
    # The fit's coefficients carry rounding (10⁻¹⁰ here, 10⁻⁹ allowed), which the free run
    # accumulates over the slowest mode's memory, 1/(1 − |λ|max) ≈ 500 samples.
    x, y = clean(4.0, 99)
    simulated = simulate_vector(model, 4.0, x, y)
    memory = 1 / (1 - np.max(np.abs(poles)))
    assert np.max(np.abs(simulated - y)) < 1e-9 * memory * np.max(np.abs(y))
    s = np.log(poles[poles.imag > 0]) / CHAIN.ts
    frequencies, damping = modal_parameters(model, 4.0, 1 / CHAIN.ts)
    order = np.argsort(np.abs(s))
    # A pole moved by δλ (≤ 10⁻⁹, as above) moves s = fs·ln λ by fs·δλ/|λ|: relative to |s|,
    # δλ/|ln λ|, largest for the slowest mode; ζ = −Re s/|s| is that over ζ itself.
    rtol = 1e-9 / np.min(np.abs(np.log(poles)))
    expected_damping = -s.real[order] / np.abs(s)[order]
    np.testing.assert_allclose(frequencies, np.abs(s)[order] / (2 * np.pi), rtol=rtol)
    np.testing.assert_allclose(damping, expected_damping, rtol=rtol / np.min(expected_damping))


def test_the_magnitude_tests_share_alpha_by_sidak_as_the_scalar_chains_do():
    """Each of M modes' two-sided magnitude tests is at α_M = 1 − (1 − α)^{1/M}: its critical
    |k̂|/σ̂_k is z_{1−α_M/2}, as the module says and models.inspection's magnitude tests use."""
    from scipy import special

    x, y = record("k2", 0.0, 3)
    models = [fit_vector_fnarx(s, experiments(s, slice(0, 5))) for s in ("k2", "k3")]
    inspection = inspect_vector(x, y, models, alpha=0.05)
    alpha_m = 1 - 0.95 ** (1 / 2)
    assert inspection.z_critical == pytest.approx(special.ndtri(1 - alpha_m / 2), rel=1e-12)
