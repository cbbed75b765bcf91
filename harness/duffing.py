"""A mass on a damper and a hardening spring, ÿ + 2ζω₀ẏ + ω₀²y + k₃y³ = u, simulated from its
differential equation: Silverbox's physics, lightly damped and finely sampled, with an offset on
the sensor, for the loop to meet from a linear start of many lags."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from harness.multisines import multisine


@dataclass(frozen=True)
class DuffingOscillator:
    """The oscillator's natural ``frequency`` (Hz), damping ratio and sampling rate ``fs``."""

    frequency: float = 60.0
    damping_ratio: float = 0.05
    fs: float = 610.0

    def respond(self, force: np.ndarray, cubic: float, substeps: int = 20) -> np.ndarray:
        """The displacement at each sample of ``force`` (held over each sample interval), from rest,
        by fourth-order Runge–Kutta at ``substeps`` steps a sample; ``cubic`` is k₃."""
        omega = 2 * np.pi * self.frequency
        parameters = np.array([2 * self.damping_ratio * omega, omega**2, cubic], dtype=np.float64)
        return _respond(np.asarray(force, dtype=np.float64), parameters, 1.0 / (self.fs * substeps), substeps)

    def record(
        self, samples: int, cubic_share: float, noise_share: float, offset_share: float, seed: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """A random-phase multisine force (periods of 1024 samples) whose amplitude grows five-fold
        over the record, as Silverbox's arrow does, and the displacement in units of its standard
        deviation, with white noise and a constant offset of those shares of it. k₃ is
        ``cubic_share`` of the linear stiffness at the linear response's standard deviation."""
        rng = np.random.default_rng(seed)
        force = multisine(1024, -(-samples // 1024), rng)[:samples] * np.linspace(0.2, 1.0, samples)
        spread = float(np.std(self.respond(force, 0.0)))
        y = self.respond(force, cubic_share * (2 * np.pi * self.frequency) ** 2 / spread**2)
        y = y / np.std(y)
        return force, y + noise_share * rng.standard_normal(samples) + offset_share


@numba.njit(cache=True)
def _respond(force: np.ndarray, parameters: np.ndarray, h: float, substeps: int) -> np.ndarray:
    c, k, k3 = parameters
    y, v = 0.0, 0.0
    out = np.zeros(force.size)
    for t in range(force.size):
        out[t] = y
        u = force[t]
        for _ in range(substeps):
            a1 = u - c * v - k * y - k3 * y**3
            y2, v2 = y + 0.5 * h * v, v + 0.5 * h * a1
            a2 = u - c * v2 - k * y2 - k3 * y2**3
            y3, v3 = y + 0.5 * h * v2, v + 0.5 * h * a2
            a3 = u - c * v3 - k * y3 - k3 * y3**3
            y4, v4 = y + h * v3, v + h * a3
            a4 = u - c * v4 - k * y4 - k3 * y4**3
            y += h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
            v += h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
    return out
