"""A drive read through a sensor blind to the sign: the coupled electric drives' pulse counter on
a simulated belt, for the rectified-output family's tests (models.effects.reads_magnitude)."""

from __future__ import annotations

import numpy as np
from scipy import signal

# The belt's speed: a third-order low pass, a lightly damped pair and a real pole, as the coupled
# drives' rectified fits find (poles 0.95 at ±0.25 rad a sample and 0.9), unit static gain.
POLES = (0.95 * np.exp(0.25j), 0.95 * np.exp(-0.25j), 0.9)
NUMERATOR = np.array([0.0, 1.0, 0.5, 0.2])
HOLD = 5  # samples each input level is held, as the drives' uniform input is


Record = tuple[np.ndarray, np.ndarray, np.ndarray]


def rectified_drive(seed: int, n: int = 500, noise: float = 0.02, offset: float = 0.0) -> Record:
    """x, the readings |z| + white noise of std ``noise``, and the signed speed z, over ``n``
    samples: x uniform on [−1.5, 2.5] (the drives' first record's range) raised by ``offset`` (the
    second record's input sits 0.5 above the first's), held ``HOLD`` samples, so that z turns
    sign every few dozen samples. The record starts at rest at the offset's speed (the gain is
    one), as a record taken in operation does."""
    rng = np.random.default_rng(seed)
    x = np.repeat(rng.uniform(-1.5, 2.5, n // HOLD + 1), HOLD)[:n]
    denominator = np.real(np.poly(POLES))
    z = signal.lfilter(NUMERATOR * np.sum(denominator) / np.sum(NUMERATOR), denominator, x) + offset
    x = x + offset
    return x, np.abs(z) + noise * rng.standard_normal(n), z
