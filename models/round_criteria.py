"""The criteria a round of the refinement loop decides by (:mod:`models.refinement`, steps 2–4),
each asked by :mod:`models.growing` in turn: the families scored on the one-step residual
(:func:`scored`) and judged on the check blocks' free run best first (:func:`judged_in_turn`),
the one-step criterion's look ahead at contenders that gain more (:func:`looked_ahead`), a
diverging family judged by output error (:func:`by_output_error_grown`), the simulation
criterion (:func:`by_simulation`), a pair of families that run free better only together
(:func:`as_pair`), and the rectifier where the records read as a magnitude
(:func:`rectified_first`). The gains a round reports (:class:`Gain`) and the least-squares fit
every phase makes of a structure (:func:`fitted_on_all`) are here too."""

from __future__ import annotations

from collections.abc import Callable, Generator, Iterator, Sequence
from dataclasses import dataclass, replace
from functools import partial
from itertools import islice
from typing import NamedTuple, get_args

import numpy as np

from models.checking import CHECK_EVALUATIONS, CheckSplit, Matters, Structure, clears
from models.effects import OFFSET, POLYNOMIAL, RECTIFIED, Effect, offset_effect, records_output_limits, unused
from models.narx import NARX, Saturation
from models.refinement_report import Criterion, Stage
from models.regression import Workers
from models.scoring import (
    EffectScore,
    FitsOnAll,
    Records,
    Scores,
    ScoringKept,
    first_row,
    fit_model_kept,
    score_effects,
)
from models.terms import Term, max_lag, parse_terms

# The significance level of the families' partial F tests, before the Bonferroni correction.
DEFAULT_ALPHA = 0.01
# A family added on the simulation error alone must lower the check blocks' free-run RMS by this
# share at least: SEMP's threshold (Piroddi & Spinelli 2003), here relative, whatever the number of
# families compared. It is not the level of the best of them: where an unmeasured force drives much
# of the output, the free run over a few hundred check samples is a noisy figure, and on clean
# records of the 2-DOF rig without its cubic spring the best of a round's families of no effect
# often takes a fifth off it, and more (docs/benchmarks/planted.md, "The simulation criterion's
# level"). A threshold set from that null, the same for every record, asks more than effects
# that the held-out data confirm take off shorter, quieter records.
SIMULATION_GAIN = 0.2
# Families judged at once on the check blocks, in a round (the workers' judgements run side by
# side): of Silverbox's ten rounds from linear:4,4, four add the first family judged, and the
# others the second to the fourth.
JUDGED_AT_ONCE = 2
# Once a family clears the one-step criterion's margin, this many more in the one-step order are
# judged on the check blocks for a larger gain (:func:`looked_ahead`).
CONTENDERS = 4
# The exponent of the linear law, which every structure the loop grows holds: a searched law
# between it and an integer law can blend the two (:func:`integer_law_first`).
LINEAR = 1.0
# A family added, the criterion that decided, the structure with it and that structure's check
# blocks' free-run RMS.
Decision = tuple[EffectScore, Criterion, Structure, float]


@dataclass(frozen=True)
class Question:
    """What a round's criteria judge its families against: the ``current`` structure and its check
    blocks' free-run RMS ``check``, those blocks' noise ``margin``
    (:func:`models.checking.check_noise`), the families' ``kinds`` by name, and the estimation
    ``records`` with their ``checks`` split."""

    current: Structure
    check: float
    margin: float
    kinds: dict[str, str]
    records: Records
    checks: CheckSplit


def scored(
    records: Records,
    current: Structure,
    offered: Sequence[Effect],
    alpha: float,
    workers: Workers,
    threads: Workers,
    rank: bool = False,
    kept: ScoringKept | None = None,
    lag: int | None = None,
    level: float | None = None,
) -> Scores:
    """Every offered family's score against ``current``'s one-step residual
    (:func:`models.scoring.score_effects`); with ``rank``, with all its regressors ranked by error
    reduction, significant or not: what the simulation criteria try. ``kept``: the loop's
    scoring of a model, kept for its next scoring of the same model; ``lag`` and ``level``, a
    round's first row and level where a family is scored beside it."""
    return score_effects(
        records,
        current.terms,
        current.noise_lags,
        offered,
        alpha,
        rank=rank,
        saturating=current.saturating,
        workers=workers,
        threads=threads,
        kept=kept,
        lag=lag,
        level=level,
    )


def fitted_on_all(
    records: Records, structure: Structure, fits: FitsOnAll | None = None
) -> tuple[NARX, np.ndarray]:
    """``structure``'s least-squares fit on all the ``records`` (:func:`models.scoring.fit_model`);
    taken from ``fits``, the fits a loop made on these records, where it made this one, and kept
    there otherwise."""
    terms = structure.terms
    return fit_model_kept(
        records, terms, structure.noise_lags, max_lag(terms), structure.saturating, structure.rectified, fits
    )


def _with(score: EffectScore, question: Question) -> list[Structure]:
    """The structures adding the scored effect to the ``question``'s current one may give: one,
    but two for output saturation (of the state or of the sensor), which adds limits rather than
    terms."""
    kinds, current = question.kinds, question.current
    if kinds.get(score.name) == "saturation":
        limits = records_output_limits(question.records)
        if limits is None:
            return []
        return [replace(current, saturating=(limits, how)) for how in get_args(Saturation)]
    if kinds.get(score.name) == "rectified":
        return [_rectified(current)]
    if score.noise_lags:
        return [replace(current, noise_lags=score.noise_lags)]
    return [replace(current, terms=current.terms + parse_terms(score.terms))]


def offered_again(effect: Effect, current: Structure) -> bool:
    """Whether ``effect`` is one the ``current`` structure has already: a saturating model is not
    offered saturation again, nor a rectified one the rectifier."""
    return (effect.kind == "saturation" and current.saturating is not None) or (
        effect.kind == "rectified" and current.rectified
    )


def _rectified(current: Structure, linear: Sequence[Term] | None = None) -> Structure:
    """``current`` read through a sensor of its magnitude, its recursion with a constant, and
    with the ``linear`` terms in place of its own where they are given: where the fold lies
    against the input's zero is the family's parameter, as a dead zone's width is (the coupled
    drives' second record, its input 0.5 above the first's: the rectified recursion runs free
    over the check blocks at 0.92 ticks/s without one)."""
    terms = current.terms if linear is None else tuple(linear)
    constant = () if Term() in terms else (Term(),)
    return replace(current, terms=terms + constant, rectified=True)


def rectified_first(
    current: Structure,
    linear: Sequence[Term],
    offered: Sequence[Effect],
    scores: Sequence[EffectScore],
    checks: CheckSplit,
    workers: Workers,
) -> Decision | None:
    """The rectified-output family, where it is offered, taken before every other (the records'
    outputs read as a magnitude), from the ``linear`` terms chosen as the rectified model's,
    wherever its output-error fit runs free over the check blocks without diverging. A sensor's
    fold is no dynamics: judged after the families of the dynamics, one of them fitted to the fold
    stands in for it first, at the orders the readings chose. Least squares cannot see the fold
    (its fit is the recursion's on the readings): a rectified structure is fitted by output error
    (:class:`models.checking.CheckSplit`), and the check figure returned is that fit's.

    The evidence is the readings' shape, never below zero and down to it, not a gain on the check
    blocks: on a record of a few hundred samples the fit part lacks the swings through zero a
    check block holds, and the rectified fit extrapolates there (the coupled drives' second
    record: its one check block holds the widest swings, and the rectified fit runs free there
    worse than the linear start, while fitted on the fit and check parts together it runs the
    held-out tail at half the start's error). What the loop returns is judged against its start
    where no choice looked (:mod:`models.held_out`)."""
    for effect, score in zip(offered, scores, strict=True):
        if effect.kind != "rectified":
            continue
        structure = _rectified(current, linear)
        (error,) = checks.judge([structure], workers, tuned=True)
        if np.isfinite(error):
            # The report lists the terms the family brings beside the rectifier: its own lags.
            brought = tuple(t.name for t in structure.terms if t not in current.terms)
            return (
                replace(score, terms=(RECTIFIED, *brought)),
                "output's range",
                structure,
                checks.error(structure),
            )
    return None


def simulation_candidates(offered: Sequence[Effect], scores: Sequence[EffectScore]) -> list[EffectScore]:
    """The scored families the simulation criteria grow the model by: those with ranked terms,
    neither noise, a sinusoid of the record's time, nor saturation."""
    return [
        score
        for effect, score in zip(offered, scores, strict=True)
        if effect.kind not in ("noise", "periodic", "saturation", "rectified") and score.ranked
    ]


def judged_in_turn(
    scores: Sequence[EffectScore],
    question: Question,
    workers: Workers,
    tell: Stage,
    stage: str,
) -> Generator[tuple[EffectScore, float, Structure], Matters | None, None]:
    """Each scored family in turn with its check blocks' free-run RMS and structure, the best
    of those adding it may give (:func:`_with`); ``tell`` is told each, in the ``stage``, as its
    judgement is read. ``JUDGED_AT_ONCE`` families are judged at a time by ``workers``: the round
    ends at the first that passes, and a family judged beside it is judged in vain. A caller that
    needs only the figures that matter to it sends which do (:meth:`CheckSplit.judge`'s
    ``matters``): the families judged from then on may give a bound for one that does not."""
    matters = None
    for first in range(0, len(scores), JUDGED_AT_ONCE):
        batch = [(score, _with(score, question)) for score in scores[first : first + JUDGED_AT_ONCE]]
        errors = question.checks.judge(
            [option for _, options in batch for option in options], workers, matters=matters
        )
        for score, options in batch:
            tell(f"{stage}: {score.name} on the check blocks")
            error, structure = min(((next(errors), option) for option in options), key=lambda trial: trial[0])
            matters = (yield score, error, structure) or matters


def looked_ahead(
    first: Decision,
    judged: Generator[tuple[EffectScore, float, Structure], Matters | None, None],
    question: Question,
    ahead: Callable[[Structure, float], tuple[float, str | None, int]],
) -> tuple[Decision, int]:
    """The family a round adds: ``first``, the first in the one-step order to clear the margin,
    unless one of the next ``CONTENDERS`` still ``judged`` takes a further ``SIMULATION_GAIN`` of
    the current model's figure ``question.check`` off the check blocks' free run and, each added in
    turn and the round after judged (``ahead``: the check figure that round ends at, the family it
    adds and the families it judged), the pair it starts ends lower by more than the figure's
    standard error ``question.margin``, and without the first; and how many candidates the look
    compared on the check blocks beside ``first`` (the contenders, and the families each round after
    judged), which the round reports among those it tried.

    The one-step order carries what the free run cannot: a family that explains more of the
    residual is more likely the effect, and an approximation of a missing effect can simulate the
    check blocks better until that effect is in (Silverbox from ``linear:4,4``: the cubic spring
    simulates them at half the missing lags' figure, and after it no named family's
    least-squares model runs free). But the first to clear can be a stand-in whose small gain
    hides the effect for good (Silverbox from ``linear:10,10``: a hysteresis variable at 0.85 of
    the figure where the offset reaches 0.38; with it in, the offset never entered). Neither
    gain alone tells these apart; the next round does: the effect leaves what remains to be
    found, a stand-in leaves its own error. A further gain of ``SIMULATION_GAIN``, what the
    simulation criterion asks of a family picked among many, decides when to look: any smaller is
    within what the best of several gains by chance on the same blocks. A later family
    that brings the first's terms among its own is that effect with more terms, not another (on
    the rig, whose structure holds a cubic spring, an offset brings every lag's square, a
    quadratic spring some of them); and where the later family's round adds the first, both pairs
    hold the same effects: in either case the one-step order names them. Moving-average
    noise, which clears by being no worse and is there to unbias the parameters, does not
    contend.

    Noise that clears first is looked past like any other first: its
    one-step rank is the colour of the residual, and every effect the process lacks colours it,
    while its model runs free as the current one does. A contender of the process that takes the
    further share off the check blocks' free run is what that colour came from. Noise is offered
    again each round, its lags growing, so the round after it need not add the contender, and
    where the two pairs end alike the process comes first, as a NARMAX's process terms are
    chosen before its noise terms: noise keeps the round only where its pair ends lower by more
    than the margin, its unbiased parameters leading the next round further.
    """
    _, criterion, structure, error = first
    current, check, margin = question.current, question.check, question.margin
    noise_first = structure.noise_lags != current.noise_lags
    # The contenders judged from here need exact figures only where they could be chosen (a
    # partial, for the workers that judge them).
    contends = partial(_contends, check, margin, error)
    looked = list(islice(_sending(judged, contends), CONTENDERS))
    contenders = [
        (other_error, other, other_structure)
        for other, other_error, other_structure in looked
        if other_structure.noise_lags == current.noise_lags
        and other_error <= (1 - margin) * check
        # Noise brings no terms a later family could hold again.
        and (noise_first or not set(structure.terms) <= set(other_structure.terms))
    ]
    if not contenders:
        return first, len(looked)
    best_error, best, best_structure = min(contenders, key=lambda trial: trial[0])
    if not contends(best_error):
        return first, len(looked)
    best_end, after_best, after_best_tried = ahead(best_structure, best_error)
    if after_best == first[0].name and not noise_first:
        return first, len(looked) + after_best_tried
    first_end, _, after_first_tried = ahead(structure, error)
    tried = len(looked) + after_best_tried + after_first_tried
    contender = (best, criterion, best_structure, best_error)
    if noise_first:
        # Noise keeps the round only where the parameters it unbiases lead further.
        return (first if first_end < (1 - margin) * best_end else contender), tried
    if best_end < (1 - margin) * first_end:
        return contender, tried
    return first, tried


def integer_law_first(
    first: Decision,
    offered: Sequence[Effect],
    scores: Scores,
    question: Question,
    workers: Workers,
    threads: Workers,
    alpha: float,
) -> tuple[Decision, int]:
    """The family a round adds where the one-step criterion decided ``first``: ``first``, unless it
    is a law whose exponent was searched (``Effect.integer_laws``), found between the linear law and
    an integer law of its signal on offer, and that integer law, with the law's exponent searched
    again beside it, ranks before the law alone by the round's own criterion, the sum of the two's
    BIC changes against the law's (each term a parameter, the exponent counted in both); the integer
    law is then added where its model clears the ``question.margin`` below ``question.check`` on the
    check blocks, and the law is offered again the round after, beside it. Also how many structures
    it judged on the check blocks.

    A law at an exponent between two integer laws can blend them with an effect beside them: on
    the 2-DOF rig, whose own cubic spring holds a Hertzian contact's |y|^1.5 beside it, a single
    law at p ≈ 2.2 explains more of the linear start's one-step residual than the cubic alone,
    and the check blocks' free run cannot tell it from the cubic with the contact law beside it,
    but over another record it is the worse model. Whether the residual holds two effects is
    what the decomposition's one-step fit says: the integer law and the law searched beside it
    explain what the blend does and more, by as much as their further terms are worth, where the
    blend is the effect; where the law is the only effect, the integer law beside it explains
    next to nothing. A law outside the two (a softening one, p < 1, beside the cubic) blends
    neither: an integer law that explains something beside it is another effect, for its own
    round (on the coupled drives' second record, the rectified output's law at p = 0.68 gave way
    to the cubic, and the model ran free over the test part half as far off again)."""
    law, current = first[0], question.current
    family = next((effect for effect in offered if effect.name == law.name), None)
    if family is None or not family.integer_laws or not law.terms:
        return first, 0
    exponent = parse_terms(law.terms[:1])[0].factors[0].parameter
    if exponent is None:
        return first, 0
    between = {
        name
        for name, integer in family.integer_laws
        if min(LINEAR, integer) < exponent < max(LINEAR, integer)
    }
    lag = first_row(current.terms, offered)
    best: tuple[float, EffectScore, Structure] | None = None
    for integer in scores.scores:
        if integer.name not in between or not integer.significant:
            continue
        beside = replace(current, terms=current.terms + parse_terms(integer.terms))
        (again,) = scored(
            question.records, beside, [family], alpha, workers, threads, lag=lag, level=scores.level
        ).scores
        together = integer.bic_change + again.bic_change
        if together < law.bic_change and (best is None or together < best[0]):
            best = (together, integer, beside)
    if best is None:
        return first, 0
    _, integer, structure = best
    (error,) = question.checks.judge([structure], workers)
    if not error <= (1 - question.margin) * question.check:
        return first, 1
    return (integer, first[1], structure, error), 1


def _contends(check: float, margin: float, error: float, other_error: float) -> bool:
    """Whether a contender's check figure ``other_error`` clears the ``margin`` below ``check``
    and takes the further gain off the first's ``error`` (:func:`looked_ahead`)."""
    return other_error <= (1 - margin) * check and error - other_error >= SIMULATION_GAIN * check


def _sending(
    judged: Generator[tuple[EffectScore, float, Structure], Matters | None, None], matters: Matters
) -> Iterator[tuple[EffectScore, float, Structure]]:
    """The families still to be ``judged`` in turn (:func:`judged_in_turn`), told first which
    figures matter."""
    try:
        yield judged.send(matters)
    except StopIteration:
        return
    yield from judged


def next_round(
    records: Records,
    families: Sequence[Effect],
    alpha: float,
    margin: float,
    checks: CheckSplit,
    workers: Workers,
    threads: Workers,
    tell: Stage,
    kept: ScoringKept,
    number: int,
    current: Structure,
    check: float,
) -> tuple[float, str | None, int]:
    """The check blocks' free-run RMS at which round ``number`` from ``current`` (running free
    there at ``check``) ends by the one-step criterion with least-squares parameters, the family
    it adds, and how many families it judged there; ``check`` and None where no named family
    clears (:func:`looked_ahead`).
    Least squares alone, as the round looked from judged its families: a branch that only output
    error could carry on would otherwise win by the estimator (output error's figures run lower),
    not by its effect."""
    offered = [
        effect
        for effect in unused([follow(effect, current.terms) for effect in families], current.terms)
        if effect.name != POLYNOMIAL and not (effect.kind == "saturation" and current.saturating is not None)
    ]
    tell(f"round {number}, looked ahead: scoring {len(offered)} families")
    scores = scored(records, current, offered, alpha, workers, threads, kept=kept)
    kinds = {effect.name: effect.kind for effect in offered}
    significant = sorted((s for s in scores.scores if s.significant), key=lambda s: s.bic_change)
    stage = f"round {number}, looked ahead"
    question = Question(current, check, margin, kinds, records, checks)
    judged = judged_in_turn(significant, question, workers, tell, stage)
    for tried, (score, error, structure) in enumerate(judged, start=1):
        if error <= (1.0 if structure.noise_lags > current.noise_lags else 1 - margin) * check:
            return min(error, check), score.name, tried
    return check, None, len(significant)


def as_pair(
    significant: Sequence[EffectScore],
    question: Question,
    ahead: Callable[[Structure, float], tuple[float, str | None, int]],
) -> tuple[tuple[Decision, float] | None, int]:
    """Where no family clears on its own, the first ``significant`` family in the one-step order
    (not moving-average noise) added with the one the round after it adds (``ahead``, judged as
    :func:`looked_ahead` judges a pair): its score, criterion, structure and check figure (worse
    than ``question.check`` alone), and the check figure the pair ends at, or None unless that end
    takes ``SIMULATION_GAIN`` of ``question.check`` off the check blocks' free run; and how many
    structures were judged on the check blocks to decide it.

    Two effects can each make the free run worse alone and simulate far better together: each
    alone is fitted to the other's share of the residual as well as its own. On the rig with
    Coulomb friction planted, nothing declared, the friction explains nearly all of the linear
    start's one-step residual, and alone runs free worse than the start, as does the rig's own
    cubic spring alone, which the friction's residual hides from the one-step tests; the two
    together run free at a small fraction of the start's figure. The family the residual names
    most strongly goes first; the next round, scored on its residual, finds its partner. The
    pair is picked through two rounds of choices, so it must take off what the simulation
    criterion asks of a family picked among many."""
    first = next((score for score in significant if not score.noise_lags), None)
    if first is None:
        return None, 0
    options = _with(first, question)
    judged = [
        (question.checks.error(option), option)
        for option in options
        if option.noise_lags == question.current.noise_lags
    ]
    if not judged:
        return None, 0
    error, structure = min(judged, key=lambda trial: trial[0])
    if not np.isfinite(error):
        return None, len(judged)
    end, partner, partner_tried = ahead(structure, error)
    tried = len(judged) + partner_tried
    if partner is None or partner == first.name or end > (1 - SIMULATION_GAIN) * question.check:
        return None, tried
    return ((first, "pair", structure, error), end), tried


def leader_as_pair(
    first: Decision,
    significant: Sequence[EffectScore],
    rejected: Sequence[str],
    question: Question,
    ahead: Callable[[Structure, float], tuple[float, str | None, int]],
) -> tuple[Decision, int]:
    """The family a round adds where the one-step criterion decided ``first`` on a fall of the check
    blocks' free run short of ``SIMULATION_GAIN``, after the family the one-step order puts first
    (the leader, not moving-average noise) ran free worse alone and was ``rejected``: ``first``,
    unless the leader judged as a pair (:func:`as_pair`: with the family the round after it adds,
    ``ahead``, ending ``SIMULATION_GAIN`` of ``question.check`` below it) ends lower than ``first``
    with the family its own round after adds, by more than the figure's standard error
    ``question.margin``; and how many structures were judged on the check blocks to decide it.

    A fall short of what the simulation criterion asks of a family picked among many is within
    what the best of several gains by chance, and the pair criterion, which judges a leader that
    runs free worse alone, is asked only where no family clears: a stand-in that clears by a
    little would otherwise keep the effect the residual names most strongly out of the round for
    good, as :func:`looked_ahead` keeps a stand-in from hiding a later family. On the rig with
    power-law damping planted (1600 samples, nothing declared) the damping law explains nearly all
    of the linear start's one-step residual, and alone, without the rig's cubic spring, runs free
    twice as far off as the start; Coulomb friction, its stand-in, cleared on a fall of 7 %, and
    the law was never in the model. Judged alike, pair against pair, the two choices differ only
    in which family leads."""
    chosen, criterion, structure, error = first
    leader = next((score for score in significant if not score.noise_lags), None)
    if (
        criterion != "one-step"
        or leader is None
        or leader.name == chosen.name
        or leader.name not in rejected
        or structure.noise_lags != question.current.noise_lags
        or error <= (1 - SIMULATION_GAIN) * question.check
    ):
        return first, 0
    paired, tried = as_pair([leader], question, ahead)
    if paired is None:
        return first, tried
    decided, pair_end = paired
    first_end, _, first_tried = ahead(structure, error)
    if pair_end < (1 - question.margin) * first_end:
        return decided, tried + first_tried
    return first, tried + first_tried


def by_output_error_grown(
    significant: Sequence[EffectScore], question: Question, workers: Workers
) -> Decision | None:
    """Where no ``significant`` family clears the one-step criterion by least squares, the first
    in the one-step order whose least-squares model diverges on the check blocks and which clears
    it by output error: its new terms added at zero to the current model's output-error fit,
    which runs free as that model does, and searched from there (:meth:`CheckSplit.search_grown`);
    its score, structure and check figure (by output error). None where none does.

    Least squares fits each lag's nonlinear term to the one-step residual, and on finely sampled
    data a small error in a lightly damped model's many coefficients makes the free run diverge,
    where the same terms with parameters fitted to the free run are an effect: on Silverbox from
    ``linear:10,10``, once the cubic spring and the offset are in, every family's least-squares
    model diverges there, and the loop stopped with the damping's and the spring's other terms
    missing. Such a family is judged against the current model's best figure, by least squares,
    by output error, or by output error searched as long again as the family is (its search
    starts where the current model's ended, and a longer search can gain on its own).
    A family whose least-squares model runs free and does not clear has been judged.
    """
    current, checks = question.current, question.checks
    diverged = [
        (score, structure)
        for score in significant
        for structure in _with(score, question)
        if structure.noise_lags == current.noise_lags
        and structure.saturating == current.saturating
        and not np.isfinite(checks.error(structure))
    ]
    if not diverged:
        return None
    start = checks.tuned(current)
    longer = CheckSplit(checks.fit, checks.check, _tuned={current: start})
    further = longer.search(current, start, CHECK_EVALUATIONS)
    baseline = min(question.check, checks.error(current, tuned=True), further)
    for score, structure in diverged:
        (error,) = checks.search_grown(current, [structure], CHECK_EVALUATIONS, workers)
        if error <= (1 - question.margin) * baseline:
            return score, "output error", structure, error
    return None


def by_simulation(
    offered: Sequence[Effect],
    scores: Sequence[EffectScore],
    current: Structure,
    checks: CheckSplit,
    workers: Workers,
) -> tuple[Decision | None, Gain | None, int]:
    """The family added on the simulation error alone, if one lowers the check blocks' free
    run enough (:mod:`models.refinement`, step 4): its score with the terms that won, the structure, and
    the check blocks' free-run RMS with it (least squares, as the other rounds report it); the
    gain of that family by output error (else the best judged's, None where none was); and how
    many structures were simulated. The structures are judged by ``workers``."""
    families = [
        (
            score,
            [
                tuple(name for label in score.ranked[:k] for name in label)
                for k in range(1, len(score.ranked) + 1)
            ],
        )
        for score in simulation_candidates(offered, scores)
    ]
    grown = {
        names: replace(current, terms=current.terms + parse_terms(names))
        for _, prefixes in families
        for names in prefixes
    }
    errors = dict(zip(grown, checks.judge(list(grown.values()), workers), strict=True))
    trials: list[tuple[float, EffectScore, Structure]] = []
    for score, prefixes in families:
        names = min(prefixes, key=errors.__getitem__)
        if np.isfinite(errors[names]):
            trials.append((errors[names], replace(score, terms=names), grown[names]))
    if not trials:
        return None, None, len(grown)
    # The current structure's best simulation, whichever its parameters: its output-error fit can
    # fail to come to rest where its least-squares fit does (on unrelated white x and y the 2-DOF
    # structure's did), and against an infinite baseline any family would pass.
    baseline = min(checks.error(current, tuned=True), checks.error(current))
    # Output error for the two best only: each costs a search, and a family whose least-squares
    # model is far behind does not overtake by its parameters alone.
    best = sorted(trials, key=lambda trial: trial[0])[:2]
    tuned = checks.judge([structure for *_, structure in best], workers, tuned=True)
    judged: Gain | None = None
    for (error, score, structure), tuned_error in zip(best, tuned, strict=True):
        gain = Gain(fall(tuned_error, baseline), SIMULATION_GAIN)
        if tuned_error <= (1 - SIMULATION_GAIN) * baseline:
            return (score, "simulation", structure, error), gain, len(grown)
        judged = better_gain(judged, gain)
    return None, judged, len(grown)


def output_state_by_simulation(
    first: Decision,
    states: Sequence[EffectScore],
    current: Structure,
    check: float,
    checks: CheckSplit,
    workers: Workers,
) -> tuple[Decision | None, int]:
    """A family whose regressors are a state of the output (the hysteresis family's Bouc–Wen
    variable of y), judged on its free run where the one-step criterion decided ``first``: of
    ``states``, such families' scores with their regressors ranked by error reduction
    (significant or not), the one whose least-squares model, its regressors in that order, takes
    ``SIMULATION_GAIN`` of the current model's figure ``check`` off the check blocks' free run
    beyond what ``first`` took; and how many structures were simulated.

    Such a state is a smooth function of the output's past, and the one-step test that ranks
    the families reads it beside the residual's own recent past, which predicts it one step
    ahead: there the state explains little that those lags do not, and moving-average noise, or
    a family that explains the residual's next value, takes the round. What tells a hysteretic
    restoring force from a linear one is the simulation, whose error such a force leaves when
    missing: so it is judged on the share of that error the simulation criterion asks of a
    family picked among many (the look ahead's further gain), and the one-step order does not
    name it second."""
    chosen, _, _, first_error = first
    if not np.isfinite(check):
        return None, 0
    trials = [
        (score, replace(current, terms=current.terms + parse_terms(names)), names)
        for score in states
        if score.name != chosen.name
        for names in (
            tuple(label for labels in score.ranked[:k] for label in labels)
            for k in range(1, len(score.ranked) + 1)
        )
    ]
    bar = first_error - SIMULATION_GAIN * check
    # Only a figure within the bar can decide: one whose run over the check blocks is beyond it
    # is not asked whether it comes to rest, and that run's RMS, a bound below its figure,
    # leaves both the best and whether it clears the bar as they were (CheckSplit.judge; a
    # partial, for the workers that judge them).
    errors = checks.judge([structure for _, structure, _ in trials], workers, matters=partial(clears, bar))
    error, best = min(zip(errors, trials, strict=True), key=lambda trial: trial[0], default=(np.inf, None))
    if best is None or error > bar:
        return None, len(trials)
    score, structure, names = best
    return (replace(score, terms=names), "simulation", structure, error), len(trials)


class Gain(NamedTuple):
    """The fall of the check blocks' free-run RMS a candidate brought and the fall it had to
    reach to be added, both shares of the RMS before."""

    gain: float
    threshold: float


def better_gain(judged: Gain | None, other: Gain | None) -> Gain | None:
    """The larger gain of ``judged`` and ``other``, either None where not judged."""
    if judged is None or (other is not None and other.gain > judged.gain):
        return other
    return judged


def fall(after: float, before: float) -> float:
    """The fall of a free-run RMS from ``before`` to ``after``, as a share of ``before``: −∞ where
    ``after`` diverged, 1 where only ``before`` did."""
    if not np.isfinite(after):
        return -np.inf
    return 1.0 if not np.isfinite(before) else float(1 - after / before)


def follow(effect: Effect, terms: tuple[Term, ...]) -> Effect:
    """The offset takes the current model's form (:func:`models.effects.offset_effect`): the terms
    its offset would bring, or, in a model with no power of y, the cube it shows through."""
    if effect.name != OFFSET:
        return effect
    return offset_effect(terms)
