"""Judging a model on held-out data: one-step and free-run errors and the residual's diagnostics."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy

from models.diagnostics import ResidualReport, residual_report
from models.errors import InputError
from models.narx import NARX
from models.output_error import diverged
from models.signals import minimum_samples

LJUNG_BOX_LAGS = 40
# The residual spectrum wants four Welch segments of 64 samples (its 31-bin background median
# needs 31 bins); the residual tests want models.signals.minimum_samples.
SPECTRUM_SAMPLES = 256


# The residual tests :func:`assess` skips on a part too short for them, as reports name them.
RESIDUAL_TESTS = ("ljung_box", "billings_voon", "billings_zhu", "spectrum")


@dataclass(frozen=True)
class Assessment:
    """A model's errors on held-out data: one-step and free-run RMS, and the diagnostics of its
    one-step prediction error (:func:`models.diagnostics.residual_report`); None, with the tests
    named in ``skipped``, on a part too short for them. ``diverged``: the free run left every
    bound (:func:`assess`), its RMS a figure of how far, not of how well it simulates."""

    one_step_rms: float
    free_run_rms: float
    diagnostics: ResidualReport | None
    skipped: tuple[str, ...] = ()
    diverged: bool = False

    @property
    def ljung_box_p(self) -> float:
        """Whiteness of the one-step prediction error: a small p-value means structure is left
        (NaN where the test was skipped)."""
        return self.diagnostics.ljung_box.p_value if self.diagnostics is not None else float("nan")

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible figures; a diverged free run's error becomes None."""

        def finite(value: float) -> float | None:
            return value if np.isfinite(value) else None

        return {
            "one_step_rms": finite(self.one_step_rms),
            "free_run_rms": finite(self.free_run_rms),
            "ljung_box_p": finite(self.ljung_box_p),
            "diagnostics": None if self.diagnostics is None else self.diagnostics.to_dict(series=False),
            "skipped_tests": list(self.skipped),
            "diverged": self.diverged,
        }


def assess(
    model: NARX,
    x: np.ndarray,
    y: np.ndarray,
    initial: int = 0,
    fs: float | None = None,
    t0: int = 0,
    noise: np.ndarray | None = None,
    lags: int = LJUNG_BOX_LAGS,
    transient: int = 0,
) -> Assessment:
    """Assess ``model`` on held-out (x, y) sampled at ``fs`` [Hz] (None: frequencies in cycles
    per sample).

    The first ``initial`` samples (at least the model's lags) only start the predictions and
    the simulation, as benchmark protocols prescribe; ``t0`` places (x, y) in the time base of
    the model's sinusoidal terms. The first ``transient`` samples are predicted and simulated
    but not scored: a record that starts at rest with its excitation (a multisine's first
    period) is run from its start, as the structure was, and judged after it. Started instead
    from L measured outputs where the transient ends, a model of high order with a slow mode
    carries those readings' noise for thousands of samples (F-16's multisines: a linear (10, 10)
    output-error model with a root at 0.998 ran free at 4.15 m/s² RMS so, 0.444 from the start).
    With moving-average ``noise`` coefficients c_1 … c_q (a NARMAX), the one-step prediction
    error is the innovation ε = r / C(q), C(q) = 1 + Σ c_i q⁻ⁱ, of the process residual r, started
    from rest; the free run uses the process model alone. A part too short for the residual tests
    (:func:`residual_tests_fit`) is scored by its errors alone, the tests named as skipped: a
    benchmark's test window can be a hundred samples (the coupled electric drives'). A free run that
    is not finite, or leaves ``RESTLESS`` times the largest measured output of the part scored,
    has diverged (:func:`models.output_error.diverged`): a model growing without bound can stay
    finite over a short record.
    """
    if transient < 0:
        raise InputError(f"the transient must be 0 or more samples, got {transient}")
    start_up = max(initial, model.max_lag)
    scored = max(start_up, transient)
    check_test_length(len(y), scored)
    start = start_up - model.max_lag
    xs, ys = np.asarray(x, dtype=np.float64)[start:], np.asarray(y, dtype=np.float64)[start:]
    error = model.residuals(xs, ys, t0 + start)
    if noise is not None and len(noise):
        error = scipy.signal.lfilter([1.0], np.concatenate(([1.0], noise)), error)
    L = model.max_lag
    simulated = model.simulate(xs, ys, t0 + start)[L:]
    # Rows of the error and the run from the first scored sample on.
    skip = scored - start_up
    error, simulated, xs, ys = error[skip:], simulated[skip:], xs[L + skip :], ys[L + skip :]
    free_run = float(np.sqrt(np.mean((simulated - ys) ** 2)))
    tested = residual_tests_fit(len(y), scored, lags)
    return Assessment(
        float(np.sqrt(np.mean(error**2))),
        free_run if np.isfinite(free_run) else float("inf"),
        residual_report(xs, ys, error, fs or 1.0, lags) if tested else None,
        () if tested else RESIDUAL_TESTS,
        diverged=diverged(simulated, ys),
    )


def residual_tests_fit(n: int, start_up: int, lags: int = LJUNG_BOX_LAGS) -> bool:
    """Whether a test part of ``n`` samples, ``start_up`` of them starting the model (or run
    through its transient), holds enough for the residual tests and spectrum."""
    return n >= residual_samples(start_up, lags)


def residual_samples(start_up: int, lags: int = LJUNG_BOX_LAGS) -> int:
    """The samples a test part needs for the residual tests and spectrum after ``start_up``."""
    return max(minimum_samples(lags, start_up), start_up + SPECTRUM_SAMPLES)


def check_test_length(n: int, start_up: int) -> None:
    """Refuse a test part with nothing to judge a model on once ``start_up`` samples have started
    it (or run through its transient)."""
    if n <= start_up:
        raise InputError(
            f"the test part has {n} samples; judging a model needs at least {start_up + 1} "
            f"({start_up} to start it and at least one to score)"
        )
