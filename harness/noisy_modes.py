"""Fault modes of the accelerometer chain (harness/accelerometer.py) trained from simulator
records at known magnitudes, with the sensors' noise on both channels: what
tests/test_free_run_inspection.py and bench/noisy_modes.py inspect records with."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

import numpy as np

from harness.accelerometer import record, scenario
from models.fnarx import FNARX, fit_fnarx
from models.free_run_inspection import FreeRunMode, fit_free_run_modes
from models.output_error import estimated_start_error
from simulator.chain import ChainParameters

# An ARX(4, 4) with no delay: the chain's driving-point acceleration to well below the sensors'
# noise (its exact order is 6; the two roots left out move the response by about 10⁻⁴ of it, a
# hundredth of the noise), and the fewer the autoregressive lags, the better their coefficients
# are determined at 1 kHz. Fewer would not do: an ARX(3, 3) misses the response by a quarter of
# the noise and follows none of the far spring's loosening, which the ARX(4, 4) follows.
TERMS = [f"y[t-{i}]" for i in range(1, 5)] + ["x[t]"] + [f"x[t-{i}]" for i in range(1, 5)]
MAGNITUDES = (0.0, 5.0, 10.0, 15.0)  # the experiments' loosening, percent
EXPERIMENT_SAMPLES = 8000
# The far spring's experiments reach beyond the range its records are watched over: what fixes
# its mode's slope is Σ(k − k̄)² times each experiment's information on k, nine times as much from
# 0 … 45 % as from 0 … 15 % at the same cost, and the chain's ARX coefficients are affine in one
# spring's stiffness (a rank-one change of the stiffness matrix moves the transfer function's
# numerator and denominator affinely), so θ₀ + k·δ holds out there too. From 0 … 15 % the slope's
# error across the chain's change was about as large as the change itself, and the mode's k̂
# shrank towards 0 under it (bench/noisy_modes.py designs).
FAR_MAGNITUDES = (0.0, 15.0, 30.0, 45.0)
# k2 is the spring next to the driving point; k3 the farthest, whose loosening the driving point
# hardly feels (its k̂ is an order of magnitude less certain).
SPRINGS = ("k2", "k3")


def experiments(
    spring: str, seed: int, magnitudes=MAGNITUDES, samples: int = EXPERIMENT_SAMPLES, repeats: int = 1
) -> list:
    """``repeats`` records of ``samples`` at each of ``magnitudes``, each at a seed of its own."""
    ks = [k for k in magnitudes for _ in range(repeats)]
    return [(*record(scenario(spring, k), samples, seed + i), k) for i, k in enumerate(ks)]


def free_run_modes(
    springs=SPRINGS,
    seed: int = 50_000,
    magnitudes=MAGNITUDES,
    samples: int = EXPERIMENT_SAMPLES,
    repeats: int = 1,
) -> list[FreeRunMode]:
    """One mode a spring, fitted jointly for their free runs, each from its own simulated
    experiments at ``magnitudes`` (a mapping gives each spring its own), ``repeats`` records of
    ``samples`` at each."""
    return fit_free_run_modes(
        {
            spring: experiments(
                spring,
                seed + 100 * index,
                magnitudes[spring] if isinstance(magnitudes, Mapping) else magnitudes,
                samples,
                repeats,
            )
            for index, spring in enumerate(springs)
        },
        TERMS,
    )


def equation_error_modes(springs=SPRINGS, seed: int = 50_000) -> list[FNARX]:
    """The paper's fault modes (:func:`models.fnarx.fit_fnarx`) from the same experiments."""
    return [
        fit_fnarx(experiments(spring, seed + 100 * index), TERMS, name=spring)
        for index, spring in enumerate(springs)
    ]


def driving_point(params: ChainParameters, frequencies: np.ndarray) -> np.ndarray:
    """The simulator's scheme from the force to mass 1's acceleration at ``frequencies`` (rad a
    sample): x[t+2] = A1·x[t+1] + A0·x[t] + e1·Ts²/m1·F[t], a[t] = (x[t+2] − 2x[t+1] + x[t])/Ts²."""
    A1, A0 = params.recursion()
    drive = np.zeros(params.n)
    drive[0] = params.ts**2 / params.masses[0]
    z = np.exp(1j * frequencies)
    return np.array(
        [
            (q - 1) ** 2 / params.ts**2 * np.linalg.solve(q * q * np.eye(params.n) - q * A1 - A0, drive)[0]
            for q in z
        ]
    )


def perfect_sigma_k(spring: str, samples: int) -> float:
    """σ_k [%] of a model that knew the chain exactly, on one record: the Cramér–Rao bound from
    the record's spectral (Whittle) information on k, the force white and the error the sensors'
    noise, σ²_y plus σ²_x through the structure: 1/σ²_k = N·mean_ω |∂G/∂k|²·σ²_F / (σ²_y + |G|²·σ²_x).
    No fault-mode model trained from noisy experiments does better."""
    healthy = scenario()
    frequencies = np.linspace(0, np.pi, 4097)[1:-1]
    response = driving_point(healthy.params, frequencies)
    step = 0.01  # percent: the response is linear in k far beyond
    slope = (driving_point(healthy.params.with_fault(spring, step), frequencies) - response) / step
    noise = healthy.y_noise_std**2 + np.abs(response) ** 2 * healthy.x_noise_std**2
    information = samples * np.mean(np.abs(slope) ** 2 * healthy.excitation_std**2 / noise)
    return float(1 / np.sqrt(information))


def slope_against_truth(mode: FreeRunMode, k: float = 12.0) -> tuple[float, float, float]:
    """The mode's change of the driving point's response from 0 to ``k`` against the chain's, on
    a noise-free record: Δ̂ = a·Δ + r, a the share along the chain's change Δ (1 for a right
    slope), |r|/|Δ| the share across it; and the healthy point's RMS misfit there."""
    noise_free = replace(scenario(), y_noise_std=0.0, x_noise_std=0.0)
    x, y = record(noise_free, 4000, 99_000)
    _, loosened = record(replace(noise_free, fault="k3", k=k), 4000, 99_000)
    lag = mode.model.max_lag
    healthy = estimated_start_error(mode.model.narx_at(0.0), x, y)[lag:]
    change = healthy - estimated_start_error(mode.model.narx_at(k), x, y)[lag:]
    truth = (loosened - y)[lag:]
    along = float(change @ truth / (truth @ truth))
    across = float(np.linalg.norm(change - along * truth) / np.linalg.norm(truth))
    return along, across, float(np.sqrt(np.mean(healthy**2)))
