"""Whether the input drives a linear ARX candidate: its input coefficients jointly significant,
and x[t] among them where it claims a delay of 0 (:func:`feeds_through`).

A linear start whose input coefficients are negligible only extrapolates the output's own past,
however well it may run free over a few check blocks. Ljung's practice for the input delay reads
the same evidence: the leading coefficients of the input that lie within their uncertainty of
zero are the delay, not the dynamics. On the 2-DOF rig the input reaches the output at x[t−4]
alone (the forward-difference scheme, SPEC §2), so that an ARX whose input lags stop short of it
has input coefficients whose true value is zero; where a nonlinearity makes every linear model
run free poorly, the free run alone cannot tell such a model from one that holds the delay.

The test is the F test of the input coefficients as a block, in the candidate's least-squares
fit on all the records: the classic test of a block of regressors, consistent on the rig whatever
an effect does to the equation error, since an input that has not reached the output yet is
independent of it. Where the output saturates (:func:`models.effects.output_limits`), only the
equations clear of the limits are used, as a saturating sensor's model is fitted
(:func:`models.narx.fitted_rows`): on a plateau the reading does not follow the input at all, and
the equations around it would hide the input's effect on the rest. The same test of x[t] alone
reads the delay: 0 only where the input at the same sample is significant.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import special

from models.effects import records_output_limits
from models.narx import fitted_rows
from models.scoring import Records
from models.terms import Term, max_lag, stacked_regressors


def input_drives(records: Records, terms: Sequence[Term], level: float) -> bool:
    """Whether the input coefficients of the linear ``terms`` (those reading x), fitted by least
    squares on ``records``, are jointly significant at ``level`` by their F test against the
    model without them. True where the test cannot be made (no input term, or too few
    equations): that is no evidence against the input."""
    inputs = np.array([_reads(term, lag=None) for term in terms])
    return _block_significant(records, terms, inputs, level)


def feeds_through(records: Records, terms: Sequence[Term], level: float) -> bool:
    """Whether the input at the same sample, x[t], is significant among the linear ``terms``
    fitted by least squares on ``records``: its F test at ``level`` against the model without
    it. True where ``terms`` have no x[t] or the test cannot be made.

    A delay of 0 says the input reaches the sampled output within the sample it is applied in
    (an accelerometer under a force); sampled dynamics otherwise answer one sample later at the
    earliest. Where x[t]'s coefficient lies within its uncertainty of zero, the delay is one or
    more (Ljung's reading of the leading input coefficients), and a model with x[t] is the model
    with delay 1 and one needless parameter, which on a few hundred samples runs free better by
    the chance of its check blocks as often as not. On the rig, whose force reaches the output at
    x[t-4], x[t] is independent of the equation error whatever an effect does to it."""
    direct = np.array([_reads(term, lag=0) for term in terms])
    return _block_significant(records, terms, direct, level)


def _reads(term: Term, lag: int | None) -> bool:
    """Whether ``term`` reads the input x (at ``lag``, or at any lag for None)."""
    return any(factor.signal == "x" and lag in (None, factor.lag) for factor in term.factors)


def _block_significant(records: Records, terms: Sequence[Term], block: np.ndarray, level: float) -> bool:
    """Whether the ``block`` of ``terms`` (a mask) is significant at ``level`` by its F test in
    their least-squares fit on ``records`` against the fit without it; the equations on an
    output's plateaus left out (module docstring). True where the test cannot be made."""
    lag = max_lag(terms)
    usable = [(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)) for x, y in records]
    usable = [(x, y) for x, y in usable if len(y) > lag]
    if not block.any() or block.all() or not usable:
        return True
    Phi, target, _ = stacked_regressors(list(terms), usable, lag)
    limits = records_output_limits(usable)
    if limits is not None:
        kept = np.concatenate([fitted_rows(y, lag, limits, "sensor") for _, y in usable])
        Phi, target = Phi[kept], target[kept]
    equations, parameters, size = len(target), Phi.shape[1], int(block.sum())
    if equations <= parameters:
        return True
    full, restricted = _residual_sum(Phi, target), _residual_sum(Phi[:, ~block], target)
    if full <= 0.0:
        return restricted > 0.0
    f_value = (restricted - full) / size / (full / (equations - parameters))
    return float(special.fdtrc(size, equations - parameters, f_value)) < level


def _residual_sum(Phi: np.ndarray, target: np.ndarray) -> float:
    """The residual sum of squares of ``target``'s least-squares fit on ``Phi``'s columns, each
    scaled to unit norm first (an output in metres beside a force in kilonewtons)."""
    norms = np.linalg.norm(Phi, axis=0)
    scaled = Phi / np.where(norms > 0, norms, 1.0)
    theta, *_ = np.linalg.lstsq(scaled, target, rcond=None)
    residual = target - scaled @ theta
    return float(residual @ residual)
