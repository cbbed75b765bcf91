"""The amplitude range of a model: up to what scale of its estimation records' inputs its free
run stays bounded.

A polynomial NARX model identified on records of some amplitude is valid there; beyond it a term
of degree above one outgrows the linear ones, and the free run may escape. That is no defect of
the identification: the exact discrete model of a hardening spring (a Duffing oscillator) escapes
too, at some multiple of the amplitude it was identified at. So the range is measured and
reported, as a careful identifier states a polynomial model's range of validity, and no model is
refused for it.

The measure: the model runs free over each estimation record with its input scaled by s, started
from the record's first L measured outputs scaled by s, for each s of ``SCALES`` in turn. The run
has diverged at s where :func:`models.output_error.diverged` says so against the record's output
scaled by s (not finite, or beyond ``RESTLESS`` times its largest value): a model whose output
grows with its input as the system's does stays within that bound. The range is the largest
scale up to which no run diverged, and the first that did.

A model linear in its output and input (plain lags and a constant) is not run beyond s = 1: its
free run at scale s is s times its run driven by the input and started from the measured
outputs, plus the constant's response, which does not grow with s. Bounded at the records' own
amplitude, it is bounded at any: its range has no limit.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from models.narx import NARX
from models.output_error import diverged
from models.simulation import FreeRun

# The scales of the estimation inputs tried, in turn. One is the records' own amplitude, where a
# model fitted and checked on them must hold. Quarter steps up to 1.5: test records a little
# louder than the estimation ones are the common case, and there the range decides whether a
# diverging test run is the model's extrapolation. Then 2 and 3: a hardening spring's exact
# discrete model escapes at a few times the amplitude it was identified at, and a polynomial
# beyond three times it is no one's claim. Each scale costs one free run a record.
SCALES = (1.0, 1.25, 1.5, 2.0, 3.0)


@dataclass(frozen=True)
class AmplitudeRange:
    """The largest scale of the estimation inputs up to which a model's free run stayed bounded
    (``bounded_to``: 0 where it diverged at the records' own amplitude, inf where it has no
    limit, a model linear in its output and input) and the first scale at which it diverged
    (``diverges_at``; None where none of ``SCALES`` did, or where there is no limit)."""

    bounded_to: float
    diverges_at: float | None

    @property
    def limited(self) -> bool:
        """Whether the model diverged at some scale tried."""
        return self.diverges_at is not None

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible: ``bounded_to`` None where the range has no limit, and the range in
        words (:meth:`describe`)."""
        return {
            "bounded_to": self.bounded_to if np.isfinite(self.bounded_to) else None,
            "diverges_at": self.diverges_at,
            "description": self.describe(),
        }

    def describe(self) -> str:
        """In words, e.g. 'bounded for inputs up to 1.5× the estimation records' amplitude,
        diverging at 2×'."""
        if not np.isfinite(self.bounded_to):
            return "bounded for inputs of any amplitude (linear in its output and input)"
        if self.diverges_at is None:
            return (
                f"bounded for inputs up to {self.bounded_to:g}× the estimation records' amplitude, "
                "the most tried"
            )
        if self.bounded_to == 0.0:
            return "diverging at the estimation records' own amplitude"
        return (
            f"bounded for inputs up to {self.bounded_to:g}× the estimation records' amplitude, "
            f"diverging at {self.diverges_at:g}×"
        )


@dataclass(frozen=True)
class AmplitudeRanges:
    """The amplitude ranges of a refinement's declared (or linear start) and refined models over
    the estimation records, and the ``scales`` tried."""

    declared: AmplitudeRange
    refined: AmplitudeRange
    scales: tuple[float, ...] = SCALES

    @property
    def narrower(self) -> bool:
        """Whether the refined model diverges at a scale the declared one stays bounded at."""
        return self.refined.bounded_to < self.declared.bounded_to

    def to_dict(self) -> dict[str, Any]:
        return {
            "scales": list(self.scales),
            "declared": self.declared.to_dict(),
            "refined": self.refined.to_dict(),
        }


def amplitude_ranges(
    declared: NARX,
    refined: NARX,
    records: Sequence[tuple[np.ndarray, np.ndarray]],
    scales: Sequence[float] = SCALES,
) -> AmplitudeRanges:
    """Both models' amplitude ranges over the estimation ``records`` (:func:`amplitude_range`)."""
    return AmplitudeRanges(
        amplitude_range(declared, records, scales),
        amplitude_range(refined, records, scales),
        tuple(sorted(scales)),
    )


def amplitude_range(
    model: NARX,
    records: Sequence[tuple[np.ndarray, np.ndarray]],
    scales: Sequence[float] = SCALES,
) -> AmplitudeRange:
    """``model``'s amplitude range over the estimation ``records`` (x, y), trying ``scales`` in
    increasing order (module docstring); a model's sinusoids count time from each record's
    start."""
    scales = sorted(scales)
    bounded_to = 0.0
    for scale in scales:
        if not all(_bounded(model, x, y, scale) for x, y in records if len(y) > model.max_lag):
            return AmplitudeRange(bounded_to, scale)
        bounded_to = scale
        if linear(model):
            return AmplitudeRange(np.inf, None)
    return AmplitudeRange(bounded_to, None)


def linear(model: NARX) -> bool:
    """Whether ``model`` is linear in its output and input: every term a plain lag of y, x, dy or
    dx, or the constant, and nothing clipping or rectifying its output."""
    plain = all(
        not term.factors
        or (
            len(term.factors) == 1
            and term.factors[0].power == 1
            and term.factors[0].function == ""
            and term.factors[0].signal in ("y", "x", "dy", "dx")
        )
        for term in model.terms
    )
    return plain and model.output_limits is None and not model.rectified


def _bounded(model: NARX, x: np.ndarray, y: np.ndarray, scale: float) -> bool:
    """Whether ``model``'s free run over the record (x, y), input and starting outputs scaled by
    ``scale``, stays within the divergence bound of its output scaled so."""
    L = model.max_lag
    run = model.run_free(FreeRun.build(model.terms, scale * np.asarray(x, dtype=np.float64)), scale * y[:L])
    return not diverged(run[L:], scale * y[L:])
