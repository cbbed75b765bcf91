"""A single-degree-of-freedom oscillator with a Bouc–Wen hysteretic restoring force, simulated
from its differential equations: the physics of Noël and Schoukens' hysteretic benchmark, with
parameters of a test's own choosing, for the loop to meet with nothing declared."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from harness.multisines import multisine


@dataclass(frozen=True)
class BoucWenOscillator:
    """m·ÿ + c·ẏ + k·y + z = u with ż = α·ẏ − β·|ẏ|·z − γ·ẏ·|z| (Bouc–Wen, n = 1), y in metres,
    u in newtons. With β + γ < 0 (γ negative and larger than β) z stiffens as y moves on from
    where it turned, as in the benchmark; ``fs`` the sampling rate."""

    mass: float = 1.0
    damping: float = 8.0
    stiffness: float = 1.5e4
    alpha: float = 2.0e4
    beta: float = 2.0e3
    gamma: float = -3.0e3
    fs: float = 500.0

    def respond(self, force: np.ndarray, substeps: int = 20) -> np.ndarray:
        """The displacement at each sample of ``force`` (held over each sample interval), from rest,
        by fourth-order Runge–Kutta at ``substeps`` steps a sample."""
        parameters = np.array(
            [self.mass, self.damping, self.stiffness, self.alpha, self.beta, self.gamma], dtype=np.float64
        )
        return _respond(np.asarray(force, dtype=np.float64), parameters, 1.0 / (self.fs * substeps), substeps)

    def record(
        self, samples: int, force_std: float, noise_std: float, seed: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """A random-phase multisine force of ``force_std`` over the lower half of the band, periods of
        1024 samples, and the displacement with white noise of ``noise_std`` added."""
        rng = np.random.default_rng(seed)
        period = 1024
        force = force_std * multisine(period, -(-samples // period), rng)[:samples]
        return force, self.respond(force) + noise_std * rng.standard_normal(samples)


@numba.njit(cache=True)
def _respond(force: np.ndarray, parameters: np.ndarray, h: float, substeps: int) -> np.ndarray:
    m, c, k, alpha, beta, gamma = parameters
    state = np.zeros(3)  # y, ẏ, z
    out = np.zeros(force.size)

    def rate(s: np.ndarray, u: float) -> np.ndarray:
        y, v, z = s
        return np.array((v, (u - c * v - k * y - z) / m, alpha * v - beta * abs(v) * z - gamma * v * abs(z)))

    for t in range(force.size):
        out[t] = state[0]
        for _ in range(substeps):
            k1 = rate(state, force[t])
            k2 = rate(state + 0.5 * h * k1, force[t])
            k3 = rate(state + 0.5 * h * k2, force[t])
            k4 = rate(state + h * k3, force[t])
            state = state + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return out
