"""How much of a test record lies outside the data its model was identified on.

A model identified on records that excite a band of frequencies and a range of amplitudes is
validated there only: beyond them its free run extrapolates, however well it simulates within.
F-16's full-grid multisines excite 2–15 Hz; the benchmark's special odd multisines (1–60 Hz) put
76 % of their input's power beyond that band, where the best linear output-error model of
acceleration 2 and the refined one (13–15 % better within the band) both leave 80–87 % of the
output's spread, the refined one 10 % more on the loudest. Three shares say how much of a test
record lies outside its estimation records:

- of its input's power, the part in frequencies the estimation inputs leave unexcited: bins of
  their Welch PSD below ``BAND_FLOOR`` times its largest value (the same bins for both, in cycles
  per sample; a record's mean is not power);
- of its samples, those whose input lies outside the range the estimation inputs span;
- and those whose output does (a hardening spring's cube reaching beyond its fitted range).

Beside them, the test record's input scale: its largest input magnitude as a multiple of the
estimation inputs' largest, the scale a model's amplitude range is told in
(:mod:`models.amplitude_range`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy

from models.errors import InputError

if TYPE_CHECKING:
    from models.scoring import Records

BAND_FLOOR = 1e-3  # 30 dB below the estimation input's strongest bin: not excited
WELCH_SAMPLES = 1024  # samples of a Welch segment, fewer for short records
EXTRAPOLATING = 0.01  # a share beyond which a test record is said to extrapolate


@dataclass(frozen=True)
class Coverage:
    """Shares of a test record outside its estimation records (module docstring): of its input's
    power outside their excited band, of its samples whose input and whose output lie beyond
    their range; and its largest input magnitude as a multiple of theirs (``input_scale``, inf
    where their inputs are all zero)."""

    outside_band: float
    input_beyond: float
    output_beyond: float
    input_scale: float

    @property
    def extrapolates(self) -> bool:
        """Whether any share exceeds ``EXTRAPOLATING``: the record judges the model partly where
        it was not identified."""
        return max(self.outside_band, self.input_beyond, self.output_beyond) > EXTRAPOLATING

    def describe(self) -> str:
        """What lies outside, in words, e.g. '76 % of its input's power outside the estimation
        records' band; 29 % of its inputs beyond their range'."""
        parts = []
        if self.outside_band > EXTRAPOLATING:
            parts.append(
                f"{_percent(self.outside_band)} of its input's power outside the estimation records' band"
            )
        beyond = [
            f"{_percent(share)} of its {name}"
            for name, share in (("inputs", self.input_beyond), ("outputs", self.output_beyond))
            if share > EXTRAPOLATING
        ]
        if beyond:
            parts.append(f"{' and '.join(beyond)} beyond their range")
        return "; ".join(parts) if parts else "within the estimation records' band and range"


def coverage(estimation: Records, x: np.ndarray, y: np.ndarray) -> Coverage:
    """How much of the test record (x, y) lies outside the ``estimation`` records (x, y pairs):
    :class:`Coverage`. The Welch segments are ``WELCH_SAMPLES`` long, or as long as the shortest
    record; the estimation PSD averages the records' by their lengths."""
    if not estimation:
        raise InputError("coverage needs the estimation records the model was identified on")
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    inputs = [np.asarray(xe, dtype=np.float64) for xe, _ in estimation]
    outputs = [np.asarray(ye, dtype=np.float64) for _, ye in estimation]
    segment = min(WELCH_SAMPLES, x.size, *(xe.size for xe in inputs))
    if segment < 2:
        raise InputError("coverage needs records of two samples or more")
    weights = np.array([xe.size for xe in inputs], dtype=np.float64)
    fitted = np.average(
        [scipy.signal.welch(xe, nperseg=segment)[1] for xe in inputs], axis=0, weights=weights
    )
    tested = scipy.signal.welch(x, nperseg=segment)[1]
    unexcited = fitted <= BAND_FLOOR * fitted.max()  # all of them where the inputs were constant
    power = float(tested.sum())
    return Coverage(
        float(tested[unexcited].sum()) / power if power > 0 else 0.0,
        _beyond(x, inputs),
        _beyond(y, outputs),
        _scale(x, inputs),
    )


def _scale(values: np.ndarray, spanned: list[np.ndarray]) -> float:
    """The largest magnitude of ``values`` over that of the ``spanned`` series."""
    largest = max(float(np.max(np.abs(s))) for s in spanned)
    magnitude = float(np.max(np.abs(values))) if values.size else 0.0
    return magnitude / largest if largest > 0 else (np.inf if magnitude > 0 else 1.0)


def _percent(share: float) -> str:
    return f"{100 * share:.0f} %"


def _beyond(values: np.ndarray, spanned: list[np.ndarray]) -> float:
    """The share of ``values`` outside [min, max] of the ``spanned`` series."""
    low = min(float(np.min(s)) for s in spanned)
    high = max(float(np.max(s)) for s in spanned)
    return float(np.mean((values < low) | (values > high)))
