"""Where the estimation records settled (:mod:`models.refinement`): the samples left out at their
start where the system had not settled.

A record often starts with the machine, before it has settled (a motor warming up from rest). Where
the structure returned is fitted by least squares, it is fitted again on the heads without their
first eighth, quarter, three eighths and half; where one of those fits runs free over the tails
better than the fit on the whole heads, beyond the comparison's uncertainty at the held-out level
split among the four, and predicts them one step ahead better, the model is estimated from where the
records settled and the report says what was left out (:func:`settled_from`). That is one more
choice the tails make, after the comparison with the start, and at a stricter level.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from models.checking import Segments, Structure
from models.errors import InputError
from models.growing import Grown
from models.held_out import HELD_OUT_ALPHA, HeldOut, compare_on_tails
from models.narx import NARX
from models.periods import excitation_period
from models.refinement_report import Stage
from models.round_criteria import fitted_on_all
from models.scoring import Records
from models.terms import WAVES, Term

# The first parts of the estimation records' heads tried as stretches where the system had not
# settled (:func:`settled_from`), as shares of each head: at most half, so that most of what the
# loop chose on stays.
SETTLING_SHARES = (0.125, 0.25, 0.375, 0.5)


def of_time(terms: Sequence[Term]) -> bool:
    """Whether any of ``terms`` holds a sinusoid of time."""
    return any(factor.signal in WAVES for term in terms for factor in term.factors)


def settled_from(
    grown: Grown, held_out: HeldOut | None, heads: Records, tails: Segments, tell: Stage
) -> tuple[int, ...]:
    """Where each estimation record's settled part begins: 0 for each, unless the structure
    :func:`models.refinement.refine` will return, fitted by least squares on the ``heads`` without a
    first share of each (``SETTLING_SHARES``), runs free over the held-out ``tails`` better than
    fitted on the whole heads beyond the comparison's uncertainty (at ``HELD_OUT_ALPHA`` split among
    the shares tried) and predicts them one step ahead better too; then where the share that gained
    most begins. A machine that changed is predicted better one step ahead as well; the free run
    over a short tail alone can favour a fit on fewer samples by chance where a lightly damped
    model's slow error drifts through every block of the comparison (the rig's records).

    A record often starts with the machine: a motor switched on from rest warms up, its friction
    and windings' resistance drifting for minutes before they settle, and a least-squares fit
    over the whole record averages the machine it became with the one it was (the DC
    motor/generator's record, which starts at rest). The tails, the record's latest samples, tell
    which. Where the structure is fitted by output error a search per share would cost as much
    as the final fit; where it holds a sinusoid of time, cutting a record moves its phase: neither
    is tried.
    """
    result = grown.refinement
    kept = bool(result.effects_added) and (held_out is None or held_out.kept)
    structure = grown.structure if kept else Structure(result.declared.terms)
    estimator = result.estimator if kept else grown.start_estimator
    settled = (0,) * len(heads)
    if estimator != "least squares" or of_time(structure.terms):
        return settled
    tell("the estimation records without their first parts, on the held-out tails")
    whole, _ = fitted_on_all(heads, structure)
    periods = [excitation_period(x) for x, _ in heads]
    best = 0.0
    for share in SETTLING_SHARES:
        # Whole periods of an input that repeats, as the heads are cut (:mod:`models.held_out`).
        cuts = tuple(
            int(len(y) * share) - (int(len(y) * share) % period if period else 0)
            for (_, y), period in zip(heads, periods, strict=True)
        )
        try:
            model, _ = fitted_on_all(
                [(x[c:], y[c:]) for (x, y), c in zip(heads, cuts, strict=True)], structure
            )
        except InputError:  # too few equations left for the structure
            continue
        judged = compare_on_tails(whole, model, tails, HELD_OUT_ALPHA / len(SETTLING_SHARES), heads=heads)
        predicts = _one_step_square(model, tails) < _one_step_square(whole, tails)
        if any(cuts) and judged.better and predicts and judged.gain > best:
            settled, best = cuts, judged.gain
    return settled


def _one_step_square(model: NARX, segments: Segments) -> float:
    """``model``'s mean square one-step prediction error over the ``segments``."""
    errors = np.concatenate([model.residuals(x, y, t0) for x, y, t0 in segments])
    return float(np.mean(errors**2))
