"""A record whose later samples lie beyond its earlier ones: an even, saturating nonlinearity in
the excitation path of a resonant second-order system, driven by steps whose size grows."""

from __future__ import annotations

import numpy as np

HOLD = 5  # samples each step of the input is held


def growing_steps(n: int, seed: int, noise: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """x: Gaussian steps scaled by an envelope that grows from 0.09 to 4; y: the response of
    y[t] = 1.5 y[t-1] − 0.7 y[t-2] + 0.3 x[t-1] + 0.5 (1 − exp(−x[t-1]²)) plus white noise.

    The even part is a square near zero and a constant beyond: a polynomial that fits it over
    the early, small steps grows without bound over the later ones, while a linear model's error
    stays bounded by it."""
    rng = np.random.default_rng(seed)
    x = np.repeat(rng.standard_normal(n // HOLD + 1), HOLD)[:n] * np.linspace(0.3, 2.0, n) ** 2
    drive = 0.3 * x + 0.5 * (1 - np.exp(-(x**2)))
    y = np.zeros(n)
    for t in range(2, n):
        y[t] = 1.5 * y[t - 1] - 0.7 * y[t - 2] + drive[t - 1]
    return x, y + noise * rng.standard_normal(n)
