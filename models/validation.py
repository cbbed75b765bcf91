"""Model validation on held-out data: one-step, k-step and free-run prediction errors (SPEC §3, §7).

For a NARX model with largest lag L, on a record of N samples:

- one-step prediction ŷ[t|t−1] = φ[t]ᵀθ from measured lags, t = L … N−1;
- k-step prediction ŷ[t|t−k]: measured outputs up to t−k, the model's own predictions
  after, driven by the measured input; defined for t = L+k−1 … N−1;
- free run: simulation from the first L measured outputs, driven by x alone, t = L … N−1; a
  clipping sensor's model starts from the first L readings clear of its limits instead
  (:func:`models.narx.run_start`), as the loop's own free runs do.

Each mode is summarised by RMS(y − ŷ) and NRMSE = RMS/std(y) over the samples it predicts,
pooled over the records. A free run that diverges has infinite errors.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from models.correlation_tests import CorrelationTest, residual_autocorrelation
from models.errors import InputError
from models.narx import NARX, run_start, sensor_limits
from models.signals import checked_record, checked_records


@dataclass(frozen=True)
class PredictionErrors:
    """RMS and NRMSE of one prediction mode over ``samples`` predicted samples."""

    rms: float
    nrmse: float
    samples: int

    def to_dict(self) -> dict[str, Any]:
        return {"rms": self.rms, "nrmse": self.nrmse, "samples": self.samples}


@dataclass(frozen=True)
class Validation:
    """Errors of the three prediction modes on held-out records; ``steps`` is k."""

    one_step: PredictionErrors
    k_step: PredictionErrors
    free_run: PredictionErrors
    steps: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "one_step": self.one_step.to_dict(),
            "k_step": {**self.k_step.to_dict(), "steps": self.steps},
            "free_run": self.free_run.to_dict(),
        }


@dataclass(frozen=True)
class OneStepFit:
    """A record against a model's one-step predictions (the paper's Figure 3).

    ``measured`` is y[t], ``predicted`` ŷ[t|t−1] = φ[t]ᵀθ and ``residual`` e[t] = y[t] − ŷ[t],
    for t = L … N−1 (in the units of y); ``autocorrelation`` is the residual's φ_ee(τ),
    τ = 1 … h, with its bands (:func:`models.correlation_tests.residual_autocorrelation`).
    """

    measured: np.ndarray
    predicted: np.ndarray
    residual: np.ndarray
    autocorrelation: CorrelationTest


def one_step_fit(model: NARX, x: ArrayLike, y: ArrayLike, lags: int = 40, alpha: float = 0.05) -> OneStepFit:
    """The one-step predictions of ``model`` on the record (x, y) and its residual's whiteness."""
    xa, ya = checked_record(x, y, model.max_lag + 1)
    predicted = model.predict(xa, ya)
    measured = ya[model.max_lag :]
    residual = measured - predicted
    return OneStepFit(measured, predicted, residual, residual_autocorrelation(residual, lags, alpha))


def k_step_predictions(model: NARX, x: ArrayLike, y: ArrayLike, steps: int, t0: int = 0) -> np.ndarray:
    """ŷ[t|t−k] for every t (NaN for t < L + k − 1); k = 1 is the one-step prediction.

    With Z_m[t] = ŷ[t|t−m] and Z_0 = y, the m-step predictions follow for all t at once:
    Z_m[t] = φ[t]ᵀθ with each lagged output y[t−i] read from Z_{m−i} when i < m and from y
    otherwise (a difference dy[t−i] takes each of its two samples so), so k passes over the
    record replace a recursion per origin. Sinusoids count t from sample ``t0`` at the record's
    start, as :meth:`NARX.predict` does.
    """
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise InputError(f"the prediction horizon must be an integer >= 1, got {steps!r}")
    L = model.max_lag
    xa, ya = checked_record(x, y, L + steps)
    n = ya.size
    predictions = [ya]
    for m in range(1, steps + 1):
        start = L + m - 1
        times = np.arange(t0 + start, t0 + n, dtype=np.float64)

        def lagged_y(i: int, m: int = m, start: int = start) -> np.ndarray:
            return (predictions[m - i] if i < m else ya)[start - i : n - i]

        def lagged_x(i: int, start: int = start) -> np.ndarray:
            return xa[start - i : n - i]

        total = np.zeros(n - start)
        for term, coefficient in zip(model.terms, model.theta, strict=True):
            column = np.full(n - start, coefficient)
            for factor in term.factors:
                column *= factor.values(lagged_y, lagged_x, times)
            total += column
        predicted = np.full(n, np.nan)
        predicted[start:] = total
        predictions.append(predicted)
    return predictions[steps]


def validate(
    model: NARX, records: Iterable[tuple[ArrayLike, ArrayLike]], steps: int = 10, t0: int = 0
) -> Validation:
    """One-step, ``steps``-step and free-run errors of ``model`` on held-out ``records``
    (``t0``: where they start in the time base of sinusoidal terms)."""
    L = model.max_lag
    checked = checked_records(records, L + max(steps, 1) + 1)
    modes: dict[str, tuple[list[np.ndarray], list[np.ndarray]]] = {
        "one_step": ([], []),
        "k_step": ([], []),
        "free_run": ([], []),
    }
    for x, y in checked:
        predicted = {
            "one_step": (model.predict(x, y, t0), L),
            "k_step": (k_step_predictions(model, x, y, steps, t0)[L + steps - 1 :], L + steps - 1),
            "free_run": _free_run(model, x, y, t0),
        }
        for name, (values, start) in predicted.items():
            modes[name][0].append(y[start:])
            modes[name][1].append(values)
    summary = {name: _errors(np.concatenate(ys), np.concatenate(ps)) for name, (ys, ps) in modes.items()}
    return Validation(summary["one_step"], summary["k_step"], summary["free_run"], steps)


def _free_run(model: NARX, x: np.ndarray, y: np.ndarray, t0: int) -> tuple[np.ndarray, int]:
    """The free run over (x, y) and the sample it predicts from: a clipped reading is not the
    system's output, and a run started from one rings through a lightly damped structure's
    whole record."""
    L = model.max_lag
    start = run_start(y, L, sensor_limits(model))
    return model.simulate(x[start - L :], y[start - L : start], t0 + start - L)[L:], start


def _errors(measured: np.ndarray, predicted: np.ndarray) -> PredictionErrors:
    if np.isnan(predicted).any():
        return PredictionErrors(float("inf"), float("inf"), measured.size)
    rms = float(np.sqrt(np.mean((measured - predicted) ** 2)))
    return PredictionErrors(rms, rms / float(np.std(measured)), measured.size)
