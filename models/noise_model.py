"""The refined model's noise model (SPEC §7: coloured noise that needs moving-average terms),
chosen once its process effects are settled.

A NARMAX's noise terms are chosen after its process terms, by the one-step criterion, and judged
by how they whiten the residual (Billings 2013, ch. 3 and 5; Chen, Billings & Luo 1989). In the
loop's rounds moving-average noise enters only where its extended least-squares fit, the process
re-estimated with it, runs free over the check blocks no worse than the model without it
(:mod:`models.growing`): there it is judged as what unbiases the process, by the process's free
run. But a moving-average model does not change the deterministic model, whose free run ignores
the noise terms, and where the re-estimated process runs free worse (noise on the measured input:
a moving-average model describes its equation error but does not remove its bias) the rounds
refuse the noise and the returned model's residual stays coloured, its one-step prediction
lacking what predicts it.

So once the loop has made the model it returns (the refined model, or its start), the noise
family is offered on its structure's equation error (the least-squares residual) as the rounds
offer it: the next four lags of the innovations (the residual itself at first) enter greedily,
each by its partial F test at the level α over the four lags offered, and where some enter the
moving-average order becomes the longest, the coefficients are fitted by the prediction error
(:func:`models.narmax.moving_average`) and the noise family is offered again beyond it on the
innovations that fit leaves. The coefficients reported are fitted to the returned model's own
one-step residual. The process parameters stay as the loop estimated and approved them: the noise
model changes the one-step prediction, and the free run is the one the loop judged. A model whose
rounds added noise keeps the noise model its process was estimated with.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from models.effects import Effect
from models.narmax import innovations_of, moving_average, record_lags
from models.refinement_report import Refinement, Round
from models.regression import column_norms
from models.scoring import (
    NARMAX_ITERATIONS,
    NOISE_LAGS_OFFERED,
    EffectScore,
    Records,
    fit_model,
    score_columns,
)
from models.terms import max_lag

# The noise family offered at most this many times after the rounds, its lags growing each time
# (:data:`models.scoring.NOISE_LAGS_OFFERED` an offer, as in the rounds).
NOISE_OFFERS = 10


def with_noise_model(
    result: Refinement,
    records: Records,
    family: Effect | None,
    alpha: float,
) -> Refinement:
    """``result`` with the noise model its returned model's residual needs (module docstring),
    reported as one round decided by "whiteness" (the lags that entered over the offers of the
    noise ``family``); ``result`` itself where no lag enters, where the rounds gave it a noise model
    already, or where no noise family is on offer (``family`` None). ``records`` are those the
    returned model was estimated on; ``alpha`` the level of each offer's test."""
    if family is None or result.noise.size:
        return result
    refined = result.refined
    saturating = None if refined.output_limits is None else (refined.output_limits, refined.saturation)
    # The colour tested is the structure's equation error, its least-squares residual: an
    # output-error fit's one-step residual is coloured by that fit's distance from least squares
    # as well, which is no noise (on clean records of the rig, its structure declared, it named
    # noise where the output-error fit was returned).
    least_squares, _ = fit_model(
        records,
        refined.terms,
        0,
        max_lag(refined.terms),
        saturating=saturating,
        rectified=refined.rectified,
    )
    equation_error = [least_squares.residuals(x, y) for x, y in records]
    innovations, lags, last = equation_error, 0, None
    for _ in range(NOISE_OFFERS):
        score = _offer(family, innovations, lags, alpha / NOISE_LAGS_OFFERED)
        if not score.significant:
            break
        lags, last = score.noise_lags, score
        innovations = innovations_of(equation_error, moving_average(equation_error, lags, NARMAX_ITERATIONS))
    if last is None:
        return result
    # One noise model, one round of the report: its order the lags that entered over the offers,
    # its evidence the last offer's, its RMS the innovations the model leaves.
    rms = float(np.sqrt(_sum_of_squares(innovations) / sum(e.size for e in equation_error)))
    step = Round(rms, alpha / NOISE_LAGS_OFFERED, NOISE_LAGS_OFFERED, (last,), last, "whiteness")
    # The free run is the returned model's: the noise model leaves the process as it was.
    step = replace(step, check_rms=(result.check_rms, result.check_rms))
    # The coefficients that predict the returned model's own one-step residual.
    noise = moving_average([refined.residuals(x, y) for x, y in records], lags, NARMAX_ITERATIONS)
    return replace(result, noise=noise, rounds=(*result.rounds, step))


def _offer(family: Effect, innovations: Sequence[np.ndarray], lags: int, level: float) -> EffectScore:
    """The noise ``family`` offered beyond the ``lags`` the noise model has: the innovations'
    next ``NOISE_LAGS_OFFERED`` lags, beside the first ``lags``, tested as the rounds test the
    family (:func:`models.scoring.score_columns`: greedily by the fall of the residual sum of
    squares, each by its partial F test at ``level``); the moving-average order becomes the
    longest that entered (zero where none did, as the rounds' scoring counts it)."""
    longest = lags + NOISE_LAGS_OFFERED
    columns = np.vstack([record_lags(xi, longest) for xi in innovations])
    target = np.concatenate(innovations)
    if not np.any(target):  # a residual fitted exactly has no colour to test
        return EffectScore(family.name, family.description, 0.0, 0.0, (), (), ())
    given, _ = np.linalg.qr(columns[:, :lags])
    candidates = columns[:, lags:]
    # Unit columns, as the rounds' candidates are (models.scoring._projected); a lag beyond a
    # record that short is all zeros, and stays so.
    norms = column_norms(candidates)
    candidates = candidates / np.where(norms > 0, norms, 1.0)
    labels = [(f"e[t-{k}]",) for k in range(lags + 1, longest + 1)]
    score, chosen, _ = score_columns(family, labels, candidates, target, given, target.size, level, False)
    return replace(score, noise_lags=lags + 1 + max(chosen) if chosen else 0)


def _sum_of_squares(series: Sequence[np.ndarray]) -> float:
    return float(sum(np.dot(s, s) for s in series))
