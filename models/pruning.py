"""Pruning back (SPEC §7): the terms the rounds of the loop added that the model does not need
(:mod:`models.refinement`).

After the rounds, the loop prunes back (Piroddi & Spinelli 2003): a term the rounds added goes
where the check blocks' free run without it is no higher than the figure the rounds ended at
(:func:`pruned_back`), judged as the model will be fitted: where output error
simulates better, by its output-error fit as well. The generic polynomial is tried whole where a
later effect may have made it redundant; then the terms not significant in the least-squares fit,
together, else by halves; then one at a time, those the fit needs least (smallest t statistic)
first. The pruning never takes a named effect's last term. Each round reports the candidates it
compared on the check blocks' free run, and the fall of that free run the effect added brought
(else the best judged) against the fall it had to reach; the last, what the pruning took out,
and a round whose generic block went whole says so.

Once, after the rounds, not between them. A term pruned between rounds changes what every
later round is offered and judged against, on a removal allowed for being no worse: on
Silverbox from linear:10,10, two cubic terms pruned after round 2 left round 3 to quadratic
stiffness, by the simulation criterion at the margin of its threshold, and that model drifted
over Schroeder80mV, which neither the check blocks nor the held-out tails showed. After the
rounds the effects are those the loop would choose unpruned, and the pruning only takes out
what their structure does not need.

It takes terms, never a named effect: an effect's last term stays. Its round added it for a
fall of the free run beyond a threshold; "no higher without it" on the same check blocks is
far weaker evidence, and those blocks see neither the model's long-run drift nor its
extrapolation. An effect is withdrawn whole by the checks that judge effects: the
output-error check of what the rounds added and the held-out tails. The generic polynomial
is the exception: it names nothing, and where a later round added a named effect it may
have stood in for, the pruning tries it whole (:func:`_generic_blocks`; its round then
reports it pruned whole).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import cached_property, partial

import numpy as np

from models.checking import CheckSplit, Structure, clears
from models.effects import POLYNOMIAL
from models.narx import z_quantile
from models.refinement_report import Round
from models.regression import Workers
from models.round_criteria import DEFAULT_ALPHA
from models.terms import Term

# Removals of one term the pruning judges on the free run at once, the smallest t statistics,
# once the batches of terms not significant are refused (:func:`pruned_back`): the workers' fits
# run side by side, and where the first is refused the next may pass.
PRUNING_TRIALS = 2
# The terms a removal took out and the structure without them.
_Removal = tuple[tuple[Term, ...], Structure]


def pruned_back(
    current: Structure,
    declared: tuple[Term, ...],
    rounds: Sequence[Round],
    checks: CheckSplit,
    workers: Workers,
    output_error: bool,
    alpha: float = DEFAULT_ALPHA,
) -> tuple[Structure, tuple[Term, ...]]:
    """``current``, grown from ``declared`` by the ``rounds``, pruned back (Piroddi & Spinelli
    2003, SEMP's pruning), and the terms taken out in turn.

    An effect picked on one round can be made useless by a later one it stood in for (a cubic
    spring fitted before the quadratic spring it imitated), and a family's terms ride in
    together though only some of them simulate: a term the rounds added goes where the check
    blocks' free-run RMS without it is no higher than the figure the rounds ended at, as SEMP's
    pruning keeps J within (1 + ρ) of J after the addition, here with ρ = 0. The bound is on that
    figure, not on the last removal's: a removal that lowered it leaves room for one that raises
    it as much, and removals one by one cannot creep above it. No rise is allowed, not even one
    within the figure's standard error: the check blocks see neither the model's extrapolation
    nor, on short records, more than a hundred samples, and with that much allowed Silverbox from
    linear:4,4 lost six terms and ran free over the arrow 15 % worse, and the coupled drives'
    second test lost four terms and with them, on the held-out tail, its effects.

    Three passes, each judging few structures, since judging every removal on the free run,
    again after each one taken, costs a fit and a free run a term a removal (on long records as
    much as the rounds): the generic blocks whole; then the terms not significant at the loop's
    level ``alpha`` in the least-squares fit on the check split's fit parts, the smallest t
    statistic first, as many together as pass (:func:`_largest_batch`), again on what is left
    after each batch taken; then, one term at a time, the best ``PRUNING_TRIALS``
    of what is left by t statistic, ranked again after each removal, until both are refused. A
    removal is judged as the model will be fitted: its least-squares free run within the bound
    and, where the current structure simulates better by output error (``output_error``: as the
    loop will then fit it), its output-error fit's within the bound on that fit's figure; a term
    of no use to the one-step fit's free run can be one the output-error fit needs (judged by
    least squares alone, Silverbox from linear:4,4 lost such terms and ran free over the arrow
    worse). The least-squares judgements are made by ``workers``.
    """
    ceiling = _ceiling(current, checks, output_error)
    if ceiling is None:
        return current, ()
    pruned: tuple[Term, ...] = ()
    for block in _generic_blocks(current, rounds):
        if (found := _first_removal(current, [block], ceiling, checks, workers)) is not None:
            taken, current = found
            pruned += taken

    def insignificant_batch(current: Structure, pruned: tuple[Term, ...]) -> _Removal | None:
        batch = _insignificant(current, declared, rounds, pruned, checks, alpha)
        return _largest_batch(current, batch, ceiling, checks, workers)

    def one_term(current: Structure, pruned: tuple[Term, ...]) -> _Removal | None:
        trials = _removals(current, declared, rounds, pruned, checks)[:PRUNING_TRIALS]
        return _first_removal(current, [(term,) for term, _ in trials], ceiling, checks, workers)

    current, pruned = _while_found(insignificant_batch, current, pruned)
    return _while_found(one_term, current, pruned)


def _while_found(
    find: Callable[[Structure, tuple[Term, ...]], _Removal | None],
    current: Structure,
    pruned: tuple[Term, ...],
) -> tuple[Structure, tuple[Term, ...]]:
    """``current`` and the terms ``pruned`` from it, with what ``find`` takes out of it taken,
    again on what is left, until it finds nothing."""
    while (found := find(current, pruned)) is not None:
        taken, current = found
        pruned += taken
    return current, pruned


@dataclass
class _Ceiling:
    """The check blocks' free-run RMS a pruned structure may reach (:func:`pruned_back`): by least
    squares, and by output error where that is how the structure simulates better (else None),
    that figure read from ``simulated`` when a removal first needs it."""

    least_squares: float
    simulated: Callable[[], float]

    @cached_property
    def output_error(self) -> float | None:
        simulated = self.simulated()
        return simulated if simulated < self.least_squares else None


def _ceiling(current: Structure, checks: CheckSplit, output_error: bool) -> _Ceiling | None:
    """The bounds :func:`pruned_back` holds ``current``'s removals to: its figures on the check blocks;
    None where neither figure is finite (no removal could be judged). The output-error figure
    is read only where a removal passes by least squares, or the least-squares figure is not
    finite: judged ahead by a worker (:meth:`CheckSplit.judge_ahead`), the removals' least-squares
    judgements go on beside its search."""
    figure = checks.error(current)
    ceiling = _Ceiling(figure, partial(checks.error, current, tuned=True) if output_error else _never)
    if not np.isfinite(figure) and not np.isfinite(ceiling.simulated()):
        return None
    return ceiling


def _never() -> float:
    """The output-error figure of a loop that does not fit by output error."""
    return np.inf


def _first_removal(
    current: Structure,
    trials: Sequence[tuple[Term, ...]],
    ceiling: _Ceiling,
    checks: CheckSplit,
    workers: Workers,
) -> _Removal | None:
    """The first of the ``trials`` (each terms taken out together) whose removal :func:`pruned_back`
    takes, with ``current`` without it; None where none is. Their least-squares fits are judged
    by ``workers``, side by side; the output-error fits, which cost far more, only where a
    removal passes by least squares, and the next only where the one before is refused."""
    without = [replace(current, terms=tuple(t for t in current.terms if t not in trial)) for trial in trials]
    # Only a figure within the ceiling can pass: one whose run over the check blocks is beyond
    # it is not asked whether it comes to rest (CheckSplit.judge).
    judged = checks.judge(without, workers, matters=partial(clears, ceiling.least_squares))
    for trial, structure, error in zip(trials, without, judged, strict=True):
        if error <= ceiling.least_squares and (
            ceiling.output_error is None or checks.error(structure, tuned=True) <= ceiling.output_error
        ):
            return trial, structure
    return None


def _generic_blocks(current: Structure, rounds: Sequence[Round]) -> list[tuple[Term, ...]]:
    """The terms of ``current`` each round that added the generic polynomial brought, where a
    later round added an effect: the blocks :func:`pruned_back` tries whole."""
    added = [step.added for step in rounds if step.added is not None]
    present = {term.name: term for term in current.terms}
    blocks = [
        tuple(present[name] for name in score.terms if name in present)
        for score in added[:-1]
        if score.name == POLYNOMIAL
    ]
    return [block for block in blocks if block]


def _insignificant(
    current: Structure,
    declared: tuple[Term, ...],
    rounds: Sequence[Round],
    pruned: Sequence[Term],
    checks: CheckSplit,
    alpha: float,
) -> list[Term]:
    """The terms :func:`_removals` offers whose t statistic is not significant at the level
    ``alpha`` (two-sided), smallest first, as many of an effect's as leave it one."""
    effect = _effect_of(rounds, pruned)
    left = Counter(effect.values())
    critical = z_quantile(1 - alpha)
    batch = []
    for term, t in _removals(current, declared, rounds, pruned, checks):
        if t < critical and (term.name not in effect or left[effect[term.name]] > 1):
            left[effect.get(term.name)] -= 1
            batch.append(term)
    return batch


def _effect_of(rounds: Sequence[Round], pruned: Sequence[Term]) -> dict[str, int]:
    """Each term the ``rounds`` added and the pruning has left, by name, with the round that
    added it (its index)."""
    gone = {term.name for term in pruned}
    return {
        name: index
        for index, step in enumerate(rounds)
        if step.added is not None
        for name in step.added.terms
        if name not in gone
    }


def _largest_batch(
    current: Structure, batch: Sequence[Term], ceiling: _Ceiling, checks: CheckSplit, workers: Workers
) -> _Removal | None:
    """The most of ``batch``'s first terms whose removal together :func:`pruned_back` takes, found by
    doubling them (one, two, four …, then all) while the removal passes, with ``current``
    without them; None where the first alone is refused. Upwards, not down from the whole: on a
    long model, removing most of its terms at once is refused far more often than a few, and a
    refused first term then costs one judgement, not one for each halving (Silverbox from
    linear:10,10: 226 terms not significant, each halving refused down to the first)."""
    taken = None
    size = 1
    while batch:
        found = _first_removal(current, [tuple(batch[:size])], ceiling, checks, workers)
        if found is None:
            break
        taken = found
        if size == len(batch):
            break
        size = min(2 * size, len(batch))
    return taken


def _removals(
    current: Structure,
    declared: tuple[Term, ...],
    rounds: Sequence[Round],
    pruned: Sequence[Term],
    checks: CheckSplit,
) -> list[tuple[Term, float]]:
    """The terms of ``current`` :func:`pruned_back` may take out with their t statistic in its
    least-squares fit on the check split's fit parts, the smallest first: those the ``rounds``
    added, but for the last one left of an effect once ``pruned`` are out."""
    effect = _effect_of(rounds, pruned)
    left = Counter(effect.values())
    removable = [
        i
        for i, term in enumerate(current.terms)
        if term not in declared and (term.name not in effect or left[effect[term.name]] > 1)
    ]
    if not removable:
        return []
    fitted = checks.fitted(current)
    t = np.abs(fitted.theta) / np.maximum(fitted.standard_errors(), np.finfo(float).tiny)
    return [(current.terms[i], float(t[i])) for i in sorted(removable, key=lambda i: t[i])]


def without_pruned(rounds: list[Round], pruned: Sequence[Term]) -> list[Round]:
    """The ``rounds`` with the ``pruned`` terms taken from the effects that brought them, named in
    the last round's report; a round whose effect lost every term is marked pruned whole."""
    names = {term.name for term in pruned}
    if not names:
        return rounds
    result = []
    for step in rounds:
        added = step.added
        if added is not None and names & set(added.terms):
            left = tuple(n for n in added.terms if n not in names)
            step = replace(step, added=replace(added, terms=left), pruned_whole=not left)
        result.append(step)
    result[-1] = replace(result[-1], pruned=tuple(term.name for term in pruned))
    return result
