"""Periodic experiments: a random-phase multisine through a resonant filter, with output noise."""

from __future__ import annotations

import numpy as np
from scipy import signal

PERIOD = 512
FILTER = ([0.0, 0.5, 0.3], [1.0, -1.2, 0.5])  # a resonant second-order system, poles |0.71|


def multisine(period: int, periods: int, rng: np.random.Generator) -> np.ndarray:
    """A random-phase multisine over the lower half of the band, repeated ``periods`` times."""
    spectrum = np.zeros(period // 2 + 1, dtype=complex)
    lines = np.arange(1, period // 4)
    spectrum[lines] = np.exp(2j * np.pi * rng.random(lines.size))
    one = np.fft.irfft(spectrum, period)
    return np.tile(one / np.std(one), periods)


def measured(periods: int, sigma: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, the noise-free response (started from rest: the first period holds its transient) and
    y = response + white noise of standard deviation ``sigma``."""
    rng = np.random.default_rng(seed)
    x = multisine(PERIOD, periods, rng)
    clean = signal.lfilter(*FILTER, x)
    return x, clean, clean + sigma * rng.standard_normal(x.size)
