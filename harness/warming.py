"""A record that starts before the system settled: a first-order drive warming up from rest."""

from __future__ import annotations

import numpy as np


def warming_drive(n: int, seed: int, settled: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A first-order drive started from rest whose pole warms up from 0.5 to 0.8 with a time
    constant of 100 samples, y[t] = a[t]·y[t-1] + x[t-1], the input held for four samples at a
    time, with 2 % output noise; ``settled``: the pole at 0.8 throughout."""
    rng = np.random.default_rng(seed)
    x = np.repeat(rng.standard_normal(n // 4 + 1), 4)[:n]
    pole = 0.8 - (0.0 if settled else 0.3) * np.exp(-np.arange(n) / 100.0)
    y = np.zeros(n)
    for t in range(1, n):
        y[t] = pole[t] * y[t - 1] + x[t - 1]
    return x, y + 0.02 * np.std(y) * rng.standard_normal(n)
