"""Instrumental-variable estimates of a model's parameters, consistent whatever colour its noise.

Least squares on the equation error is consistent only where that error is white. Where it is
not — an unmeasured force the plant filters, noise on the measured output, the part of a
nonlinear system's output a linear model does not explain — the past outputs among the regressors
are correlated with it, and least squares' estimate is biased; a larger order then simulates
better only because its extra lags model the noise. The instrumental-variable estimate solves
Σ ζ[t]·(y[t] − φ[t]ᵀθ) = 0 instead, with instruments ζ correlated with the regressors φ but not
with the noise: here φ itself with every measured output replaced by an auxiliary model's free run,
driven by the input alone (Young's auxiliary-model instruments; IV4 of Söderström and Stoica,
*Instrumental Variable Methods for System Identification*, without its prefilter). The auxiliary
model is least squares' fit, then the first estimate itself: the better the model, the better the
instruments. On open-loop data the estimate is consistent for a linear system's transfer
function (for a nonlinear one, the input-output part the input's own past explains), at the cost of
one free run and one solve.

A structure of more lags than the system's has no unique estimate: the noise-free regressors are
then linearly dependent (A·C and B·C fit as well as A and B, for any C), the instruments' products
with the regressors nearly singular, and the estimate is what the noise makes of it; its free run
runs off. That is the instrumental-variable order test (Wellstead, 1978): an order the data do not
support is not found to simulate better.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from models.narx import NARX, fitted_rows
from models.regression import column_norms
from models.terms import stacked_regressors

# Auxiliary models the instruments are made from: least squares' fit, then the first estimate.
PASSES = 2


def fit_instrumental(model: NARX, segments: Sequence[tuple[np.ndarray, np.ndarray, int]]) -> NARX | None:
    """``model``'s terms estimated by instrumental variables on ``segments`` (x, y and the first
    sample's index in its record), ``model`` (least squares' fit, say) the first auxiliary model;
    None where an auxiliary model's free run over them diverges, so that no instruments can be made,
    or the equations are singular.

    Only terms whose output factors are plain lags make instruments (a linear structure, with a
    constant or sinusoids, is what this is for): the free run replaces y in each of them."""
    records = [(x, y) for x, y, _ in segments]
    origins = [t0 for *_, t0 in segments]
    lag = model.max_lag
    regressors, target, _ = stacked_regressors(model.terms, records, lag, origins)
    # A saturating model's equations on its limits are left out, as its least-squares fit
    # leaves them out (models.narx.fitted_rows): there the reading is not its output.
    kept = np.ones(len(target), dtype=bool)
    if model.output_limits is not None:
        kept = np.concatenate(
            [fitted_rows(y, lag, model.output_limits, model.saturation) for _, y in records]
        )
    regressors, target = regressors[kept], target[kept]
    scale = column_norms(regressors)
    estimate = model
    for _ in range(PASSES):
        runs = [(x, estimate.simulate(x, y, t0)) for x, y, t0 in segments]
        if not all(np.all(np.isfinite(run)) for _, run in runs):
            return None
        instruments = stacked_regressors(model.terms, runs, lag, origins)[0][kept]
        weights = instruments / column_norms(instruments)
        try:
            theta = np.linalg.solve(weights.T @ (regressors / scale), weights.T @ target) / scale
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(theta)):
            return None
        estimate = replace(estimate, theta=theta)
    return estimate
