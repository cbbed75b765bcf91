"""A structure that is not the rig: three masses watched by a driving-point accelerometer, with
sensor noise on both measured signals; the tests of baseline-only monitoring and
bench/novelty_rates.py watch it."""

from __future__ import annotations

import numpy as np

from simulator.chain import ChainParameters, ChainScenario, simulate_chain

# Three masses, a driving-point accelerometer at 1 kHz: heavily damped, as the explicit scheme needs.
CHAIN = ChainParameters.build(3, [10.0, 20.0, 15.0], [50e3, 80e3, 30e3], [2000.0], ts=1e-3)
FORCE = 1000.0  # N
NOISE = 0.01  # of each healthy signal's RMS, on x and on y


def scenario(fault: str = "none", k: float = 0.0, level: float = 1.0) -> ChainScenario:
    """The chain at ``level`` times the training force, its sensors' noise a floor: 1 % of the
    healthy signals' RMS at the training level, whatever the level."""
    clean = ChainScenario(CHAIN, excitation_std=FORCE, outputs=(1,), response="acceleration")
    y_rms = float(np.std(simulate_chain(clean, 20_000, 1).responses["y1"]))
    return ChainScenario(
        CHAIN, fault, k, excitation_std=level * FORCE, outputs=(1,), response="acceleration",
        y_noise_std=NOISE * y_rms, x_noise_std=NOISE * FORCE,
    )  # fmt: skip


def record(s: ChainScenario, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    simulated = simulate_chain(s, n, seed)
    return simulated.x, simulated.responses["y1"]
