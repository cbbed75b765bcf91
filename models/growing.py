"""The refinement loop's rounds on a set of records (:func:`loop_on`, :mod:`models.refinement`):
each round offers the families the current structure lacks and asks the criteria of
:mod:`models.round_criteria` in turn, the named families before the generic polynomial; after the
rounds the terms they added are pruned back (:mod:`models.pruning`), what they added is checked by
output error and, from three records on, families are grown across folds
(:mod:`models.across_folds`); last, the refined structure's parameters are estimated by whichever
of least squares and output error simulates the check blocks better, and the start as the loop
makes it when it adds nothing is kept for the comparison on the held-out tails.

Each phase is a function of what the one before returned: the settings every round runs with
(:class:`_Loop`), one round's question (:class:`_Offer`) and where its choice stands as its
criteria run (:class:`_Choosing`) are immutable and passed explicitly."""

from __future__ import annotations

from collections.abc import Callable, Generator, Iterable, Sequence
from dataclasses import dataclass, replace
from functools import partial
from itertools import compress
from typing import Any, NamedTuple

import numpy as np

from models.across_folds import as_the_folds_judged, family_across_folds, repairs_only_bias
from models.checking import (
    MIN_BLOCK,
    SETTLED_EVALUATIONS,
    CheckSplit,
    Matters,
    Segments,
    Structure,
    by_output_error,
    check_noise,
    checked_whole,
    grown_by_zeros,
)
from models.effects import HYSTERESIS, POLYNOMIAL, Effect, candidate_effects, unused
from models.errors import InputError
from models.kinks import offered_within_the_records
from models.linear_start import choose_linear, rectified_orders
from models.narx import NARX
from models.output_error import comes_to_rest, free_run_at_rest
from models.periods import pooled_period_noise
from models.pruning import pruned_back, without_pruned
from models.refinement_report import Estimator, Refinement, Round, Stage
from models.regression import Workers
from models.round_criteria import (
    SIMULATION_GAIN,
    Decision,
    Gain,
    Question,
    as_pair,
    better_gain,
    by_output_error_grown,
    by_simulation,
    fall,
    fitted_on_all,
    follow,
    integer_law_first,
    judged_in_turn,
    leader_as_pair,
    looked_ahead,
    next_round,
    offered_again,
    output_state_by_simulation,
    rectified_first,
    scored,
)
from models.scoring import EffectScore, FitsOnAll, Records, Scores, ScoringKept, first_row, fit_model
from models.signals import checked_records
from models.terms import Term, max_degree, max_lag, parse_terms


class Grown(NamedTuple):
    """What the loop made of its records: the refinement; the start as the loop fits it when it
    adds nothing (the declared structure, its parameters by ``start_estimator``) with its check
    blocks' free-run RMS; the structure refined; and, where families were grown across folds, the
    structure before them and each grown (:func:`models.across_folds.as_the_folds_judged`)."""

    refinement: Refinement
    start: NARX
    start_estimator: Estimator
    start_check: float
    structure: Structure
    folded: tuple[Structure, tuple[Structure, ...]] | None
    # The structure refined, fitted by least squares on all the records the loop ran on (the
    # refined model where that is its estimator): a caller comparing the estimators takes it
    # from here rather than fitting it again.
    least_squares: NARX
    # The least-squares fits on all the records the loop ran on that it made of its models (the
    # rounds' scorings of a NARMAX), for a caller that fits one of them there again.
    fits: FitsOnAll | None = None


# The significant families judged on the check blocks in turn (:func:`models.round_criteria.judged_in_turn`).
_InTurn = Generator[tuple[EffectScore, float, Structure], Matters | None, None]


@dataclass(frozen=True)
class _Loop:
    """What every round of :func:`loop_on` runs with: the estimation ``records`` and their check
    split, the ``families`` on offer, the loop's settings, the check blocks' noise ``margin``
    (:func:`models.checking.check_noise`) and the scorings ``kept`` for a model scored again (after
    a look ahead, by the simulation criteria)."""

    records: Records
    checks: CheckSplit
    families: list[Effect]
    alpha: float
    max_rounds: int
    output_error: bool
    margin: float
    tell: Stage
    workers: Workers
    threads: Workers
    kept: ScoringKept


@dataclass(frozen=True)
class _Offer:
    """One round's question: its ``number``, the ``current`` structure and its check blocks'
    free-run RMS ``check``, the families ``offered`` (their kinds by name) and their scores."""

    number: int
    current: Structure
    check: float
    offered: list[Effect]
    kinds: dict[str, str]
    scores: Scores


@dataclass(frozen=True)
class _Choosing:
    """Where a round's choice stands as its criteria run in turn: the family ``decided`` (None
    until one is), the gain of the effect added, else of the best judged, the candidates
    ``tried`` on the check blocks, the significant families ``rejected`` there, and the families'
    ranked scores once the simulation criterion has asked for them."""

    decided: Decision | None = None
    judged: Gain | None = None
    tried: int = 0
    rejected: tuple[str, ...] = ()
    ranked: Scores | None = None


def loop_on(
    records: Records,
    declared: Sequence[str | Term] | None,
    effects: Sequence[Effect] | None,
    alpha: float,
    max_rounds: int,
    output_error: bool,
    tell: Stage,
    workers: Workers,
    threads: Workers,
    orders: tuple[int, int, int] | None = None,
    rectified: tuple[Term, ...] | None = None,
    ranged_by: Records | None = None,
    on_structure: Callable[[Structure], object] | None = None,
) -> Grown:
    """The loop of :func:`models.refinement.refine` on all of ``records``, and what
    :func:`models.refinement.refine` needs to make its models again on more: the rounds
    (:func:`_rounds`), the pruning after them, the output-error check of what they added and the
    families grown across folds (:func:`_after_rounds`), the refined model's estimator
    (:func:`_refined_fit`) and the start (:func:`_start`). ``orders``: the linear orders
    ``declared`` was chosen with, and ``rectified`` the linear terms chosen as the rectified
    model's (:func:`models.linear_start.rectified_orders`), where the caller chose them
    (:func:`models.refinement.refine` on short records). ``ranged_by``: the records whose range
    says whether laws of the output kinked at zero are offered
    (:func:`models.kinks.offered_within_the_records`), ``records`` where not given: the whole
    records, tails too, where the caller holds tails out, as the comparison on them reads it.
    ``on_structure``: told the structure the loop refines once the rounds, the pruning and the
    checks after them have settled it, before its estimator is chosen (an output-error search on
    all the ``records``, in this process): a caller may start work that needs only that structure
    meanwhile."""
    checks = CheckSplit.of(records)
    if declared is None:
        orders, terms = choose_linear(records, checks=checks, progress=tell, workers=workers)
        rectified = rectified_orders(records, checks, tell, workers)
    else:
        terms = parse_terms(declared)
    families = offered_within_the_records(
        list(effects) if effects is not None else candidate_effects(terms),
        records if ranged_by is None else ranged_by,
    )
    checked_records(records, 1, degree=max(max_degree(terms), 3))
    _check_length(records, terms, families)
    declared_model, _ = fit_model(records, terms, 0, max_lag(terms))
    current = Structure(terms)
    check = checks.error(current)
    margin = check_noise(checks.check)
    loop = _Loop(
        records,
        checks,
        families,
        alpha,
        max_rounds,
        output_error,
        margin,
        tell,
        workers,
        threads,
        ScoringKept(),
    )
    rounds, current, check = _rounds(loop, current, check, rectified)
    declared_structure = Structure(terms)
    by_the_rounds = current
    declared_search, fitted_ahead = _sent_ahead(loop, current, declared_model, declared_structure)
    if current.terms != tuple(terms):
        rounds, current, check = _pruned_rounds(loop, terms, current, check, rounds)
    after = _after_rounds(loop, current, check, declared_structure, rounds)
    if on_structure is not None:
        on_structure(after.structure)
    fitted = fitted_ahead if after.structure == by_the_rounds else [fitted_on_all(records, after.structure)]
    return _grown(loop, after, fitted, (declared_model, declared_structure), declared_search, orders)


def _sent_ahead(
    loop: _Loop, current: Structure, declared_model: NARX, declared_structure: Structure
) -> tuple[Iterable[NARX], Iterable[tuple[NARX, np.ndarray]]]:
    """The work :func:`loop_on` sends to the workers and threads as the rounds end, to be read
    after the pruning and the checks: the declared model's output-error search on all the
    records, and the least-squares fit on them of ``current``, the rounds' structure (which the
    pruning or the checks may yet change)."""
    records, checks, workers = loop.records, loop.checks, loop.workers
    if loop.output_error and current != declared_structure:
        # The output-error judgements the pruning's bound and the check of what the rounds added
        # ask for (:func:`models.pruning.pruned_back`, :func:`_after_rounds`), searched by the
        # workers side by side from here, where this process made the first alone with the
        # workers idle and the second waited for it; the pruning's least-squares judgements
        # follow them.
        checks.judge_ahead([current, declared_structure], workers, tuned=True)
    # The declared model's output-error fit on all the records, which the final search may start
    # from, searched by a worker meanwhile, where that search waited for it (0.4 s on Silverbox);
    # with the builtin map, only when asked for. Unused when least squares simulates better.
    everything: Segments = [(x, y, 0) for x, y in records]
    declared_search = workers(
        _call,
        [partial(by_output_error, declared_model, everything, SETTLED_EVALUATIONS)]
        if loop.output_error
        else [],
    )
    # The least-squares fit on all the records of the structure the rounds grew, made by a thread
    # while the workers judge it, where this process would wait (a third of a second on
    # Silverbox's NARMAX): unless the pruning or the checks change the structure, it is the
    # refined model's, or its search's start.
    return declared_search, loop.threads(_call, [partial(fitted_on_all, records, current)])


def _pruned_rounds(
    loop: _Loop, declared: tuple[Term, ...], current: Structure, check: float, rounds: list[Round]
) -> tuple[list[Round], Structure, float]:
    """The rounds' reports, the structure and its check blocks' free-run RMS once the terms the
    rounds added are pruned back, once, after them (:func:`models.pruning.pruned_back`); the last
    round names what went."""
    loop.tell("pruning the terms the rounds added")
    checks = loop.checks
    current, pruned = pruned_back(
        current, declared, rounds, checks, loop.workers, loop.output_error, loop.alpha
    )
    if pruned:
        rounds = without_pruned(rounds, pruned)
        check = checks.error(current)
        rounds[-1] = replace(rounds[-1], check_rms=(rounds[-1].check_rms[0], check))
    return rounds, current, check


def _grown(
    loop: _Loop,
    after: _AfterRounds,
    fitted: Iterable[tuple[NARX, np.ndarray]],
    declared: tuple[NARX, Structure],
    declared_search: Iterable[NARX],
    orders: tuple[int, int, int] | None,
) -> Grown:
    """What the loop made: the refinement of the structure ``after`` the rounds, its parameters
    by the estimator that simulates better (:func:`_refined_fit`), and the start
    (:func:`_start`); ``declared``, the declared model by least squares and its structure."""
    checks, current = loop.checks, after.structure
    declared_model, declared_structure = declared
    refined, noise, estimator, declared_tuned, least_squares = _refined_fit(
        loop, after, fitted, declared_model, declared_structure, declared_search
    )
    refinement = Refinement(
        declared_model,
        refined,
        noise,
        tuple(after.rounds),
        estimator,
        orders,
        after.withdrawn,
        checks.error(current, tuned=estimator == "output error"),
        pooled_period_noise(checked_whole(loop.records)),
    )
    start, start_estimator = _start(
        loop, current, declared_structure, declared_model, declared_tuned, declared_search, refined, estimator
    )
    start_check = checks.error(declared_structure, tuned=start_estimator == "output error")
    folded = (after.before_folds, tuple(after.grown_across_folds)) if after.grown_across_folds else None
    return Grown(
        refinement, start, start_estimator, start_check, current, folded, least_squares, loop.kept.fits
    )


def _rounds(
    loop: _Loop, current: Structure, check: float, rectified: tuple[Term, ...] | None
) -> tuple[list[Round], Structure, float]:
    """The rounds from the ``current`` structure, whose check blocks' free-run RMS is ``check``,
    until one adds nothing or none is left to offer: each round's report, and the structure
    grown with its figure."""
    rounds: list[Round] = []
    for number in range(1, loop.max_rounds + 1):
        offered = unused([follow(effect, current.terms) for effect in loop.families], current.terms)
        offered = [e for e in offered if not offered_again(e, current)]
        if not offered:
            break
        kinds = {effect.name: effect.kind for effect in offered}
        loop.tell(f"round {number}: scoring {len(offered)} {'family' if len(offered) == 1 else 'families'}")
        scores = scored(
            loop.records, current, offered, loop.alpha, loop.workers, loop.threads, kept=loop.kept
        )
        step, decided = _round(loop, _Offer(number, current, check, offered, kinds, scores), rectified)
        rounds.append(step)
        if decided is None:
            break
        _, _, current, check = decided
    return rounds, current, check


def _round(loop: _Loop, offer: _Offer, rectified: tuple[Term, ...] | None) -> tuple[Round, Decision | None]:
    """One round's report and the family it adds, if any: the rectifier first where the records
    read as a magnitude, then the named families on every criterion (:func:`_tier`), then the
    generic polynomial."""
    scores = offer.scores
    step = Round(scores.residual_rms, scores.level, scores.candidates, scores.scores, None)
    choosing = _Choosing()
    if loop.output_error and offer.number == 1 and rectified is not None:
        decided = rectified_first(
            offer.current, rectified, offer.offered, scores.scores, loop.checks, loop.workers
        )
        if decided is not None:
            # Taken on the readings' shape: no fall on the check blocks it had to reach.
            choosing = _Choosing(decided, Gain(fall(decided[3], offer.check), -np.inf), tried=1)
    # The named families on both criteria first, then the generic polynomial on both: where a
    # named effect explains the data, the loop names it.
    tier = [e.name == POLYNOMIAL for e in offer.offered]
    for generic in (False, True) if choosing.decided is None else ():
        choosing = _tier(loop, offer, tier, generic, choosing)
        if choosing.decided is not None:
            break
    if (judged := choosing.judged) is not None:
        step = replace(step, tried=choosing.tried, gain=judged.gain, threshold=judged.threshold)
    if choosing.decided is None:
        return replace(step, rejected=choosing.rejected, check_rms=(offer.check, offer.check)), None
    score, criterion, _, error = choosing.decided
    step = replace(step, added=score, criterion=criterion, check_rms=(offer.check, error))
    return replace(step, rejected=choosing.rejected), choosing.decided


def _tier(loop: _Loop, offer: _Offer, tier: list[bool], generic: bool, choosing: _Choosing) -> _Choosing:
    """The round's criteria in turn on the named families (the generic polynomial if
    ``generic``): the one-step criterion with its look ahead, else output error, the simulation
    criterion and the pair."""
    significant = sorted(
        (s for s, g in zip(offer.scores.scores, tier, strict=True) if s.significant and g == generic),
        key=lambda s: s.bic_change,
    )
    question = _question(loop, offer)
    in_turn = judged_in_turn(significant, question, loop.workers, loop.tell, f"round {offer.number}")
    choosing = _by_one_step(loop, offer, in_turn, choosing)
    if choosing.decided is None and loop.output_error:
        decided = by_output_error_grown(significant, question, loop.workers)
        rejected = tuple(name for name in choosing.rejected if decided is None or name != decided[0].name)
        choosing = replace(choosing, decided=decided, rejected=rejected)
        if decided is not None:
            choosing = replace(choosing, judged=Gain(fall(decided[3], offer.check), loop.margin))
    elif choosing.decided is not None:
        choosing = _integer_law(loop, offer, choosing, choosing.decided)
        choosing = _looking_ahead(loop, offer, in_turn, choosing, choosing.decided)
        if not generic:
            choosing = _leader_in_pair(loop, offer, significant, choosing, choosing.decided)
            choosing = _output_state(loop, offer, choosing, choosing.decided)
    if choosing.decided is None and loop.output_error and generic in tier:
        choosing = _on_simulation(loop, offer, tier, generic, choosing)
    if choosing.decided is None and not generic and offer.number < loop.max_rounds:
        choosing = _in_pair(loop, offer, significant, choosing)
    return choosing


def _by_one_step(loop: _Loop, offer: _Offer, in_turn: _InTurn, choosing: _Choosing) -> _Choosing:
    """The first family of ``in_turn`` whose model lowers the check blocks' free run by more than
    its standard error, decided by the one-step criterion; those before it rejected."""
    judged, tried, rejected = choosing.judged, choosing.tried, choosing.rejected
    for score, error, structure in in_turn:
        tried += 1
        # Moving-average noise, there to unbias the parameters, need only not make it worse.
        gain = Gain(
            fall(error, offer.check), 0.0 if structure.noise_lags > offer.current.noise_lags else loop.margin
        )
        if error <= (1 - gain.threshold) * offer.check:
            return replace(
                choosing,
                decided=(score, "one-step", structure, error),
                judged=gain,
                tried=tried,
                rejected=rejected,
            )
        judged = better_gain(judged, gain)
        rejected += (score.name,)
    return replace(choosing, judged=judged, tried=tried, rejected=rejected)


def _integer_law(loop: _Loop, offer: _Offer, choosing: _Choosing, first: Decision) -> _Choosing:
    """The family the one-step criterion decided, ``first``, or the integer law a searched law
    stood in for with an effect beside it (:func:`models.round_criteria.integer_law_first`)."""
    decided, judged = integer_law_first(
        first, offer.offered, offer.scores, _question(loop, offer), loop.workers, loop.threads, loop.alpha
    )
    choosing = replace(choosing, decided=decided, tried=choosing.tried + judged)
    if decided is not first:
        choosing = replace(choosing, judged=Gain(fall(decided[3], offer.check), loop.margin))
    return choosing


def _looking_ahead(
    loop: _Loop,
    offer: _Offer,
    in_turn: _InTurn,
    choosing: _Choosing,
    first: Decision,
) -> _Choosing:
    """The family the one-step criterion decided, or a later one of ``in_turn`` that gains
    more and, the round after each judged, ends lower (:func:`models.round_criteria.looked_ahead`)."""
    ahead = _next_round(loop, loop.families, offer.number + 1)
    decided, contended = looked_ahead(first, in_turn, _question(loop, offer), ahead)
    choosing = replace(choosing, decided=decided, tried=choosing.tried + contended)
    if decided is not first:
        choosing = replace(choosing, judged=Gain(fall(decided[3], offer.check), loop.margin))
    return choosing


def _output_state(loop: _Loop, offer: _Offer, choosing: _Choosing, first: Decision) -> _Choosing:
    """The family the one-step criterion decided, ``first``, or the hysteresis family, a state of
    the output, where its free run judges it further ahead
    (:func:`models.round_criteria.output_state_by_simulation`)."""
    chosen, _, _, first_error = first
    # No free run falls below zero: where the one-step choice left less than the share to take
    # beyond it, the family cannot take it.
    beyond_reach = first_error < SIMULATION_GAIN * offer.check
    if HYSTERESIS not in offer.kinds or chosen.name == HYSTERESIS or beyond_reach:
        return choosing
    # Its regressors ranked, significant or not, on the round's equations (the model's scoring
    # and the family's search kept from the round's); its own test's level is not read.
    states = scored(
        loop.records,
        offer.current,
        [effect for effect in offer.offered if effect.name == HYSTERESIS],
        loop.alpha,
        loop.workers,
        loop.threads,
        True,
        loop.kept,
        first_row(offer.current.terms, offer.offered),
    ).scores
    decided, simulated = output_state_by_simulation(
        first, states, offer.current, offer.check, loop.checks, loop.workers
    )
    choosing = replace(choosing, tried=choosing.tried + simulated)
    if decided is None:
        return choosing
    return replace(choosing, decided=decided, judged=Gain(fall(decided[3], offer.check), SIMULATION_GAIN))


def _on_simulation(
    loop: _Loop, offer: _Offer, tier: list[bool], generic: bool, choosing: _Choosing
) -> _Choosing:
    """The tier's family whose model, its regressors in the order of their error reduction,
    lowers the check blocks' free run by ``SIMULATION_GAIN``, decided by the simulation criterion
    (:func:`models.round_criteria.by_simulation`)."""
    offer_name = "the generic polynomial" if generic else "the families"
    loop.tell(f"round {offer.number}: {offer_name} on the simulation error")
    ranked = choosing.ranked or scored(
        loop.records, offer.current, offer.offered, loop.alpha, loop.workers, loop.threads, True, loop.kept
    )
    chosen = [g == generic for g in tier]
    decided, simulated, structures = by_simulation(
        list(compress(offer.offered, chosen)),
        list(compress(ranked.scores, chosen)),
        offer.current,
        loop.checks,
        loop.workers,
    )
    judged = simulated if decided is not None else better_gain(choosing.judged, simulated)
    return replace(choosing, decided=decided, judged=judged, tried=choosing.tried + structures, ranked=ranked)


def _in_pair(loop: _Loop, offer: _Offer, significant: list[EffectScore], choosing: _Choosing) -> _Choosing:
    """The first significant family with the family the round after it adds, where together they
    lower the check blocks' free run by ``SIMULATION_GAIN`` (:func:`models.round_criteria.as_pair`)."""
    paired, paired_tried = as_pair(significant, _question(loop, offer), _partner_round(loop, offer))
    choosing = replace(choosing, tried=choosing.tried + paired_tried)
    if paired is None:
        return choosing
    decided, pair_end = paired
    return replace(
        choosing,
        decided=decided,
        rejected=tuple(name for name in choosing.rejected if name != decided[0].name),
        judged=Gain(fall(pair_end, offer.check), SIMULATION_GAIN),
    )


def _leader_in_pair(
    loop: _Loop, offer: _Offer, significant: list[EffectScore], choosing: _Choosing, first: Decision
) -> _Choosing:
    """The family the one-step criterion decided, ``first``, or the one-step order's leader that
    ran free worse alone, judged as a pair where ``first`` cleared by little and the pair ends
    lower (:func:`models.round_criteria.leader_as_pair`)."""
    ahead = _partner_round(loop, offer)
    decided, tried = leader_as_pair(first, significant, choosing.rejected, _question(loop, offer), ahead)
    choosing = replace(choosing, decided=decided, tried=choosing.tried + tried)
    if decided is first:
        return choosing
    rejected = tuple(name for name in choosing.rejected if name != decided[0].name)
    return replace(choosing, rejected=rejected, judged=Gain(fall(decided[3], offer.check), SIMULATION_GAIN))


def _question(loop: _Loop, offer: _Offer) -> Question:
    """What the round's criteria judge ``offer``'s families against (:class:`Question`)."""
    return Question(offer.current, offer.check, loop.margin, offer.kinds, loop.records, loop.checks)


def _partner_round(loop: _Loop, offer: _Offer) -> Callable[[Structure, float], tuple[float, str | None, int]]:
    """The round after ``offer``'s that finds a pair's partner (:func:`_next_round`): an effect of
    the process, not noise, which clears by being no worse and would end the pair where its first
    left it."""
    named = [effect for effect in loop.families if effect.kind != "noise"]
    return _next_round(loop, named, offer.number + 1)


def _next_round(
    loop: _Loop, families: list[Effect], number: int
) -> Callable[[Structure, float], tuple[float, str | None, int]]:
    """Round ``number`` from a structure, offering ``families``, as a look ahead judges it
    (:func:`models.round_criteria.next_round`)."""
    return partial(
        next_round,
        loop.records,
        families,
        loop.alpha,
        loop.margin,
        loop.checks,
        loop.workers,
        loop.threads,
        loop.tell,
        loop.kept,
        number,
    )


class _AfterRounds(NamedTuple):
    """The structure after the rounds' effects were checked by output error and families grown
    across folds: the rounds' reports with those, how many of the first were withdrawn, and the
    structure before the folds with each grown across them."""

    structure: Structure
    rounds: list[Round]
    withdrawn: int
    before_folds: Structure
    grown_across_folds: list[Structure]


def _after_rounds(
    loop: _Loop, current: Structure, check: float, declared_structure: Structure, rounds: list[Round]
) -> _AfterRounds:
    """What the rounds added withdrawn where it only repairs least squares' bias
    (:func:`models.across_folds.repairs_only_bias`); then, from three records on, families grown
    on the simulation error across folds (:func:`models.across_folds.family_across_folds`)."""
    records, checks = loop.records, loop.checks
    folds = [checks] + [CheckSplit.of(records, fold) for fold in (0, 2)] if len(records) >= 3 else []
    withdrawn = 0
    if loop.output_error and current != declared_structure:
        loop.tell("the effects added, checked by output error")
        if repairs_only_bias(declared_structure, current, check, folds or [checks], loop.workers):
            withdrawn = len(rounds)
            current = declared_structure
    before_folds, grown_across_folds = current, []
    if loop.output_error and folds:
        for _ in range(loop.max_rounds):
            offered = unused([follow(effect, current.terms) for effect in loop.families], current.terms)
            scores = scored(
                records, current, offered, loop.alpha, loop.workers, loop.threads, True, loop.kept
            )
            found = family_across_folds(offered, scores.scores, current, folds, loop.tell, loop.workers)
            if found is None:
                break
            score, current, errors = found
            grown_across_folds.append(current)
            step = Round(scores.residual_rms, scores.level, scores.candidates, scores.scores, None)
            rounds = [
                *rounds,
                replace(step, added=score, criterion="simulation across folds", check_rms=errors),
            ]
    return _AfterRounds(current, rounds, withdrawn, before_folds, grown_across_folds)


def _refined_fit(
    loop: _Loop,
    after: _AfterRounds,
    fitted: Iterable[tuple[NARX, np.ndarray]],
    declared_model: NARX,
    declared_structure: Structure,
    declared_search: Iterable[NARX],
) -> tuple[NARX, np.ndarray, Estimator, NARX | None, NARX]:
    """The refined structure's model on all the records, its moving-average coefficients and its
    estimator, with the declared model's output-error fit where it was searched, and its
    least-squares fit: ``fitted``, the least-squares fit, unless by output error it simulates the
    check blocks better and comes to rest."""
    records, checks, current = loop.records, loop.checks, after.structure
    # Least squares is consistent when the noise enters the equation (a force on the structure)
    # and gives the best one-step predictor; output error when the noise is on the measured
    # output. The check blocks tell which simulates better.
    simulates_better = loop.output_error and (
        current.rectified or checks.error(current, tuned=True) < checks.error(current)
    )
    ((refined, noise),) = fitted
    if not simulates_better:
        return refined, noise, "least squares", None, refined
    loop.tell("output-error fit on all the records")
    (declared_tuned,) = declared_search
    if current == declared_structure:
        # Nothing was added: the declared structure's output-error fit, not a second search
        # from other starts, which ends at another optimum of the same structure, better or
        # worse on other records by chance (F-16's acceleration 2 from the linear orders the
        # loop chose: 5–7 % worse than that fit on two test levels).
        tuned = None if declared_tuned is declared_model else declared_tuned
    elif after.grown_across_folds:
        tuned = as_the_folds_judged(
            records,
            after.before_folds,
            after.grown_across_folds,
            declared_structure,
            declared_tuned,
            loop.threads,
        )
    else:
        # The search starts from whichever simulates the estimation data best: the
        # least-squares fit; the output-error fit on the fit parts the check just made (near
        # the optimum, so that the search on all the data takes few steps); or the declared
        # model's output-error fit grown by the added terms at zero, which simulates as that
        # model does, so that the search cannot end worse than it, as it can from least
        # squares (F-16's sweeps, Wiener–Hammerstein's records).
        starts = [refined, replace(refined, theta=checks.tuned(current).theta)]
        if declared_tuned is not declared_model:
            starts.append(grown_by_zeros(declared_tuned, refined))
        start = min(starts, key=lambda model: restless_then_rms(free_run_at_rest(model, records)))
        everything: Segments = [(x, y, 0) for x, y in records]
        found = by_output_error(start, everything, SETTLED_EVALUATIONS, loop.threads)
        # The search keeps a start that comes to rest from leaving it; a start that did not
        # (least squares' fit on all the data can differ from the check's) is no better.
        tuned = None if found is start else found
    if tuned is not None and comes_to_rest(tuned, records):
        return tuned, noise, "output error", declared_tuned, refined
    return refined, noise, "least squares", declared_tuned, refined


def _start(
    loop: _Loop,
    current: Structure,
    declared_structure: Structure,
    declared_model: NARX,
    declared_tuned: NARX | None,
    declared_search: Iterable[NARX],
    refined: NARX,
    estimator: Estimator,
) -> tuple[NARX, Estimator]:
    """The start as the loop makes it when it adds nothing (:func:`_refined_fit`) and its
    estimator: by output error where that simulates the check blocks better and comes to rest."""
    checks = loop.checks
    if current == declared_structure:
        return (refined, estimator) if estimator == "output error" else (declared_model, estimator)
    if loop.output_error and checks.error(declared_structure, tuned=True) < checks.error(declared_structure):
        if declared_tuned is None:
            (declared_tuned,) = declared_search
        if declared_tuned is not declared_model and comes_to_rest(declared_tuned, loop.records):
            return declared_tuned, "output error"
    return declared_model, "least squares"


def restless_then_rms(judged: tuple[float, bool]) -> tuple[bool, float]:
    """Sort key of a start: models that come to rest first, then by free-run RMS."""
    rms, at_rest = judged
    return not at_rest, rms


def _call(function: Callable[[], Any]) -> Any:
    """``function()``: what a worker runs to call a function prepared with its arguments."""
    return function()


def _check_length(records: Records, terms: tuple[Term, ...], offered: Sequence[Effect]) -> None:
    lag = max([max_lag(terms)] + [max_lag(e.terms) for e in offered if e.terms])
    candidates = sum(e.regressors for e in offered)
    n = sum(len(y) - lag for _, y in records)
    needed = 2 * (len(terms) + candidates) + 1
    if n < needed or any(len(y) <= lag + 3 * MIN_BLOCK // 10 for _, y in records):
        raise InputError(
            f"the estimation records have {n} equations ({', '.join(str(len(y)) for _, y in records)} "
            f"samples); refining {len(terms)} terms with {candidates} candidates needs at least "
            f"{needed}, and each record more than {lag + 3 * MIN_BLOCK // 10} samples"
        )
